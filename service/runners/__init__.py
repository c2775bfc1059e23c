"""Where jobs execute: the runner interface (``base.py``), the embedded process pool (``local.py``),
the Celery runner and its worker task (``celery_runner.py``), what runs inside a worker process
(``worker.py``), and the runner the settings ask for (``factory.py``)."""
