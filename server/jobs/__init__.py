"""Background experiments (``POST /jobs``): the job worker, where its units are computed."""
