"""traffictwin.evidential."""
