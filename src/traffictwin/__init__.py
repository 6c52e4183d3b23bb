"""traffictwin: cooperative occupancy-grid fusion and stereo risk assessment as an MLOps pipeline."""

__version__ = "0.1.0"
