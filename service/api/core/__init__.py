"""Settings and the error mapping of the HTTP service."""
