"""Shared pytest fixtures: where the real data lives, and ROS isolation per test run."""

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    """../shared/data beside the clone, or $TERRAIN_NAV_DATA."""
    return Path(os.environ.get("TERRAIN_NAV_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to the real DEMs and imagery; skips the test when they are absent."""
    path = shared_data_dir()
    if not (path / "dem").is_dir():
        pytest.skip(f"real data not found at {path} (set TERRAIN_NAV_DATA)")
    return path


@pytest.fixture(scope="session")
def region():
    """A 512x512 synthetic drainage pattern: minutiae and skeleton."""
    from synthetic_minutiae import terrain_minutiae

    return terrain_minutiae((512, 512), seed=11)


@pytest.fixture(scope="session")
def other_region():
    """Another, unrelated 512x512 drainage pattern."""
    from synthetic_minutiae import terrain_minutiae

    return terrain_minutiae((512, 512), seed=12)


# Every test run gets its own DDS domain and localhost-only discovery, so parallel runs
# (CI next to a developer, two checkouts) never see each other's nodes. Set before rclpy
# initialises; node subprocesses inherit it.
os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "0")
