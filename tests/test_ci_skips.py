"""A test that cannot run here skips, except under CI=true, where it fails."""

from __future__ import annotations

import pytest
from ci_skips import skip_or_fail_on_ci


def test_skips_locally_and_fails_under_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="no tmpfs"):
        skip_or_fail_on_ci("no tmpfs")
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match=r"no tmpfs \(CI=true: not skipped\)"):
        skip_or_fail_on_ci("no tmpfs")
