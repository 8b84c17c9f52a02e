"""brdfcap.reports stage."""
