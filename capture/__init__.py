"""brdfcap.capture stage."""
