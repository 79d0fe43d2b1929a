"""The signal chain on samples: ring buffer, slide detector, spike removal, features, window analysis, pipeline, truth matching."""
