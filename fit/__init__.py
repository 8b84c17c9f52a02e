"""brdfcap.fit stage."""
