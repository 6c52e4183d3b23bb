"""traffictwin.risk."""
