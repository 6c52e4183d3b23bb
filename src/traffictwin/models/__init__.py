"""traffictwin.models."""
