"""lidarmap's mapping service: FastAPI app, job runner, storage and the command line."""
