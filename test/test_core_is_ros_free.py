"""The algorithm core must import without rclpy or any ROS message package."""

import subprocess
import sys
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / "terrain_nav_ros" / "core"


def test_importing_every_core_module_loads_no_ros():
    modules = sorted(".".join(p.relative_to(CORE.parents[1]).with_suffix("").parts)
                     for p in CORE.rglob("*.py") if p.stem != "__init__")
    code = (
        "import importlib, sys\n"
        f"for name in {modules!r}: importlib.import_module(name)\n"
        "ros = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('rclpy', 'rosidl_parser', 'sensor_msgs', 'std_msgs', 'geometry_msgs', 'nav_msgs',"
        " 'terrain_nav_msgs', 'builtin_interfaces'))\n"
        "print(','.join(ros))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=CORE.parents[1], check=True)
    assert len(modules) >= 2
    assert out.stdout.strip() == "", f"core imported ROS modules: {out.stdout}"
