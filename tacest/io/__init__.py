"""HDF5 file formats of SPEC: run, estimate and plan files."""
