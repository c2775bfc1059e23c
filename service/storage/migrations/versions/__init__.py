"""The job store's revisions, oldest first: ``v0001_initial_schema``."""
