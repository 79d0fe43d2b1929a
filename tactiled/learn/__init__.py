"""Learning: datasets of slides, model files, classifiers, the training search, scoring and the papers' experiments."""
