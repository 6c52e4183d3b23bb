"""traffictwin.io."""
