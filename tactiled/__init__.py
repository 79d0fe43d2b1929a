"""tactiled: tactile roughness sensing daemon and toolkit for a two-film PVDF fingertip.

The package imports light: heavy modules (SciPy, PyWavelets, scikit-learn) are only
imported by the modules that need them.
"""

__version__ = "0.1.0"
