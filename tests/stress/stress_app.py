"""uvicorn factory for the stress commands: the service with settings from the environment and,
when ``LIDARMAP_TEST_JOB_FUNCTION`` names one ("module:function"), an injected job function.

    python -m uvicorn stress_app:create --factory   (with tests/stress on PYTHONPATH)
"""

from __future__ import annotations

import os

from service.api.app import create_app


def create():
    return create_app(job_function=os.environ.get("LIDARMAP_TEST_JOB_FUNCTION") or None)
