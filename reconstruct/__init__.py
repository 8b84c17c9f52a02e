"""brdfcap.reconstruct stage."""
