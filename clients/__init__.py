"""Python SDK, demo scripts and the `bdf` command line."""
