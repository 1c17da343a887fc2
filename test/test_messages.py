"""Every custom message travels intact from one process to another over DDS."""

import subprocess
import sys
from pathlib import Path

import numpy as np
from message_samples import samples
from ros_helpers import SpinningNode, stop, wait_until

from terrain_nav_msgs.srv import GetDemTile


def _plain(value):
    """Message -> nested dicts and lists of plain values, NaN made comparable."""
    if hasattr(value, "get_fields_and_field_types"):
        # float32 fields hold the float32 rounding of what was assigned: compare at that width.
        return {k: _plain(np.float32(getattr(value, k)) if t == "float" else getattr(value, k))
                for k, t in value.get_fields_and_field_types().items()}
    if isinstance(value, float | np.floating):
        return "nan" if np.isnan(value) else float(value)
    if isinstance(value, list | tuple) or hasattr(value, "tolist"):
        return [_plain(v) for v in (value.tolist() if hasattr(value, "tolist") else value)]
    return value


def test_each_custom_message_round_trips_between_processes():
    expected = samples()
    publisher = subprocess.Popen([sys.executable, str(Path(__file__).with_name(
        "message_samples.py"))], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)
    listener = SpinningNode("sample_listener")
    received = {}
    try:
        for name, msg in expected.items():
            listener.node.create_subscription(
                type(msg), f"/samples/{name}", lambda m, n=name: received.setdefault(n, m), 10)
        ok = wait_until(lambda: len(received) == len(expected), 30)
        assert ok, f"received only {sorted(received)}"
    finally:
        listener.close()
        stop(publisher)
    for name, msg in expected.items():
        assert _plain(received[name]) == _plain(msg), name


def test_get_dem_tile_service_definition():
    request = GetDemTile.Request(center_frame=GetDemTile.Request.CENTER_GEODETIC,
                                 center_x=36.1, center_y=-84.2, width=256, height=128, gsd=5.0)
    assert (request.width, request.height) == (256, 128)
    response = GetDemTile.Response(success=False, message="outside the DEM")
    assert not response.success and response.tile.georef.width == 0
