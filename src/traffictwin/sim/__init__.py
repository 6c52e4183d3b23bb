"""traffictwin.sim."""
