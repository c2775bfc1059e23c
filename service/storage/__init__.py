"""Where the service keeps things: the job store (``store.py``, SQLite or PostgreSQL: its database in
``database.py``, each resource in its own module, ``session_records.py``, ``log_records.py``,
``chunk_records.py`` and ``job_records.py``) and its typed rows (``rows.py``), the data folder
(``data_dir.py``) and its free space (``disk_space.py``), uploads as they arrive (``uploads.py``) and
their inspection (``inspection.py``), streamed chunks (``chunks.py``) and the drive log they make
(``stream_log.py``)."""
