"""A real lidarmap service for client tests: ``python live_server.py DATA_DIR PORT [JOB_FUNCTION]``
serves the app with uvicorn on 127.0.0.1:PORT (JOB_FUNCTION "module:function" replaces the mapping job)."""

from __future__ import annotations

import sys
from pathlib import Path

from lidarmap.cli.serve import exit_normally_on_sigterm
from service.api.app import create_app
from service.api.server import serve
from service.settings import Settings

if __name__ == "__main__":
    data_dir, port = Path(sys.argv[1]), int(sys.argv[2])
    job_function = sys.argv[3] if len(sys.argv) > 3 else None
    exit_normally_on_sigterm()  # stopped with SIGTERM by the tests: as `lidarmap serve` is
    settings = Settings(data_dir=data_dir, workers=1)
    serve(create_app(settings, job_function=job_function), host="127.0.0.1", port=port,
          max_head_bytes=settings.max_header_bytes, log_level="warning")
