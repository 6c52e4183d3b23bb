"""traffictwin.reporting."""
