"""Hardware drivers on transports: PI GCS stages, jena piezo focus, FPGA light/trigger board, Basler cameras."""
