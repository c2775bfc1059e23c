"""What users run: the ``lidarmap`` command line (:mod:`lidarmap.cli`) and the Python client of the
service (:class:`lidarmap.client.LidarmapClient`). Built on the engine (``slam_engine``) and, for
``lidarmap serve`` and ``lidarmap worker`` only, on the service (``service``)."""
