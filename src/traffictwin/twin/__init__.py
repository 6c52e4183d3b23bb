"""traffictwin.twin: the cooperative digital twin — N vehicles' maps fused per time step, and risk from it."""
