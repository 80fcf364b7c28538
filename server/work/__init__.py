"""Background work: the lease runner and its pool of worker processes."""
