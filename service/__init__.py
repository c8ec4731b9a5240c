"""HTTP service over the tiled maps (FastAPI); built in a later issue."""
