"""Pydantic models shared by the service, the CLI and clients. Imports only pydantic and the
standard library."""
