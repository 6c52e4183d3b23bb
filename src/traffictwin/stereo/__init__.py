"""traffictwin.stereo."""
