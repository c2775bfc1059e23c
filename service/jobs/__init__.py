"""What a job is and does, independent of where it runs: its settings (``settings.py``), its memory
floor (``estimate.py``), what a job function is handed (``context.py``), the mapping job over an upload
or a stream (``mapping.py``), the live job following a stream (``live.py``), what every job writes
(``outputs.py``) and where its products lie and how they are served (``products.py``)."""
