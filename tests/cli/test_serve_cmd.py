"""`lidarmap serve`'s warning for a service open to the network without API keys, and its logging set-up.
The command itself, run as a process and stopped with SIGTERM: tests/service/test_serve_process.py."""

from __future__ import annotations

import pytest

from lidarmap.cli.serve import is_loopback, log_config, open_without_key_warning


@pytest.mark.parametrize(("host", "loopback"), [("127.0.0.1", True), ("127.0.0.2", True), ("::1", True),
                                                ("localhost", True), ("0.0.0.0", False), ("::", False),
                                                ("192.168.1.5", False), ("myhost.example", False)])
def test_loopback_addresses(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_a_warning_only_when_open_beyond_this_machine_without_keys() -> None:
    warning = open_without_key_warning("0.0.0.0", [])
    assert warning is not None and warning.startswith("warning: listening on 0.0.0.0 without API keys")
    assert "LIDARMAP_API_KEYS" in warning
    assert open_without_key_warning("0.0.0.0", ["k"]) is None
    assert open_without_key_warning("127.0.0.1", []) is None


def test_the_service_loggers_print_at_info_beside_uvicorns() -> None:
    config = log_config()
    assert config["loggers"]["lidarmap"] == {"handlers": ["default"], "level": "INFO", "propagate": False}
    assert "uvicorn.access" in config["loggers"]  # uvicorn's own set-up kept
