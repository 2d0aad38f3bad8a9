"""HDF5 file formats of SPEC: run, estimate and plan files; cutting runs and estimated
trajectories into pieces at their actions (slicing)."""
