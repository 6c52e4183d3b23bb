"""traffictwin.training."""
