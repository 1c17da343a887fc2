#!/usr/bin/env bash
# Regenerate requirements/lock.txt from requirements/requirements.in in a throw-away venv.
# pip freeze is not usable here: the ROS wheels also register egg-info entries under ROS
# package names (rclpy, std_msgs, ...) that no index serves, so keep only what pip installed.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
python3.11 -m venv "$TMP/venv"
"$TMP/venv/bin/pip" install -q -r "$REPO/requirements/requirements.in" wheel
"$TMP/venv/bin/pip" inspect | "$TMP/venv/bin/python" -c '
import json, sys
dists = json.load(sys.stdin)["installed"]
pins = sorted((d["metadata"]["name"], d["metadata"]["version"]) for d in dists
              if d.get("installer") == "pip" and d["metadata"]["name"] != "pip")
print("".join(f"{n}=={v}\n" for n, v in pins), end="")
' >"$REPO/requirements/lock.txt"
echo "wrote $(wc -l <"$REPO/requirements/lock.txt") pins to requirements/lock.txt"
