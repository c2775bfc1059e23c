"""The HTTP API: the FastAPI app (``app.py``), its routers (``routers/``, one per resource), request
dependencies (``deps.py``), the JSON error answers (``error_handlers.py``, ``openapi_errors.py``), the
body-size middleware (``limits.py``), store rows -> public schemas (``convert.py``) and the web viewer
(``viewer/static``, served by ``routers/viewer.py``)."""
