"""traffictwin.evaluation."""
