"""Hardware side of the bench: drivers (arm, ToF camera, pressure board), pose planner, HDF5 recorder."""
