"""Controllers: the MPPI core, its proposals (the plug-in point), the proposal bank, the MPPI family and CFU-MPPI."""
