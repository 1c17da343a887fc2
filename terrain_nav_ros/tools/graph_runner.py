"""Run the node graph without ``ros2 launch``: one process per node, supervised.

The graph is described once, in a YAML file (``config/graph.yaml``)::

    params_files: [terrain_nav.yaml]   # ROS 2 parameters files, relative to this file
    dds_profile: fastdds.xml           # Fast DDS XML profile for every node (optional)
    namespace: uav1                    # the nodes' namespace (optional; default the root)
    nodes:
      - name: metamap                  # node name; its block in the params files
        executable: metamap            # an entry of terrain_nav_ros.executables.NODES
        required: true                 # if it dies for good, the whole graph is stopped
        respawn: false                 # true: restarted when it dies (see below)
        enabled: true                  # false: started only when asked for by name
        parameters: {gsd: 5.0}         # overrides on top of the params files
        remappings: {/in: /out}

With a namespace (the file's ``namespace``, or ``--namespace`` on the command line,
``namespace:=`` for the launch file), every node and topic is under it (``/uav1/nav/odometry``,
``/uav1/fmu/in/vehicle_visual_odometry``: a second aircraft's graph on the same network, or
PX4's ``UXRCE_DDS_NS``), ``/tf`` and ``/tf_static`` too (``/uav1/tf``, as navigation2 does);
``/clock`` stays shared. The params files' node blocks are rewritten to the nodes' full names
for it (:func:`namespaced_params_files`).

A node with ``enabled: false`` (an optional output such as the autopilot bridge) is left out
unless :func:`load_graph` is given its name in ``enable`` (``--enable NAME`` on the command
line, ``enable:=NAME`` for the launch file).

``launch/terrain_nav.launch.py`` builds the same nodes from the same file for normal ROS
installs. The runner starts every node in its own process (and session, so a terminal's
Ctrl-C reaches only the runner), waits until all are visible in the ROS graph, prefixes their
output with their name, forwards SIGINT/SIGTERM, escalates to SIGKILL after a grace period,
and reports any node that dies.

A node with ``respawn: true`` that dies once the graph is up (a crash, a kill: any exit but
0) is started again after :data:`RESPAWN_DELAY` s, as ``ros2 launch`` does with
``respawn=True``; one that dies :data:`RESPAWN_LIMIT` times within :data:`RESPAWN_WINDOW` s
is crash-looping and is given up on: it counts as died. A node that dies during start-up is
not respawned (a bad parameter would only die again). The nodes share a folder for the run,
named by ``$TERRAIN_NAV_RUN_DIR`` (the log folder, or a temporary one removed at the end,
unless the environment names one): the ekf keeps its checkpoint there, which a respawned
ekf resumes from.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ..core.estimation.checkpoint import RUN_DIR_VARIABLE
from ..executables import NODES, SUPERVISOR_VARIABLE

# A respawned node is started again this long after it died [s] ...
RESPAWN_DELAY = 0.1
# ... unless it died this many times within this window [s]: a crash loop, given up on.
RESPAWN_LIMIT = 3
RESPAWN_WINDOW = 60.0


_GRAPH_KEYS = {"params_files", "dds_profile", "namespace", "nodes"}


class GraphError(RuntimeError):
    """The graph description is invalid, or the graph could not be brought up."""


@dataclass
class NodeSpec:
    """One node of the graph."""

    name: str
    executable: str
    required: bool = True
    enabled: bool = True
    respawn: bool = False
    parameters: dict = field(default_factory=dict)
    remappings: dict = field(default_factory=dict)


@dataclass
class GraphSpec:
    """The nodes and their shared parameters file."""

    nodes: list[NodeSpec]
    params_files: list[Path] = field(default_factory=list)
    dds_profile: Path | None = None   # Fast DDS profile XML for every node (graph.yaml)
    namespace: str = ""   # the nodes' namespace, "/uav1" ("": the root)

    def environment(self, base=None) -> dict:
        """The nodes' environment: ``base`` (default this process's) with the graph's Fast
        DDS profile, unless ``base`` names one already."""
        env = dict(os.environ if base is None else base)
        if self.dds_profile is not None and not env.get(DDS_PROFILE_VARIABLE):
            env[DDS_PROFILE_VARIABLE] = str(self.dds_profile)
        return env


# In a namespace, the transforms go to its own /tf as well (relative names resolve in it).
TF_REMAPPINGS = {"/tf": "tf", "/tf_static": "tf_static"}

# the variable rmw_fastrtps reads its XML profile from
DDS_PROFILE_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"


def load_graph(path: str | Path, enable=()) -> GraphSpec:
    """Parse and validate a graph YAML file (see the module docstring).

    The spec holds the enabled nodes, and those with ``enabled: false`` whose names are in
    ``enable``; a name in ``enable`` that the file does not have is an error. Every key must
    be of its type (``enabled: "false"`` is a string, and would be true): a mistake is a
    GraphError naming it, never a node started or left out by a guess.
    """
    path = Path(path)
    try:
        doc = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)
    except (OSError, yaml.YAMLError) as err:
        raise GraphError(f"cannot read graph file {path}: {err}") from err
    doc = {} if doc is None else doc
    _expect(doc, dict, f"{path}: the top level",
            "a mapping (params_files, dds_profile, namespace, nodes)")
    unknown = set(doc) - _GRAPH_KEYS
    if unknown:
        raise GraphError(f"{path}: unknown keys {sorted(unknown)} (known: "
                         f"{', '.join(sorted(_GRAPH_KEYS))})")
    names = doc.get("params_files") or []
    names = [names] if isinstance(names, str) else names
    _expect(names, list, f"{path}: params_files", "a file name or a list of them")
    params_paths = []
    for name in names:
        _expect(name, str, f"{path}: params_files entry {name!r}", "a file name")
        params_paths.append((path.parent / name).resolve())
    for params_path in params_paths:
        if not params_path.is_file():
            raise GraphError(f"{path}: params file {params_path} does not exist")
    entries = doc.get("nodes") or []
    _expect(entries, list, f"{path}: nodes", "a list of node entries")
    nodes = [_node_spec(path, entry) for entry in entries]
    names = [n.name for n in nodes]
    if len(set(names)) != len(names):
        raise GraphError(f"{path}: duplicate node names in {names}")
    params_docs = [_check_params_file(params_path, set(names) | set(NODES))
                   for params_path in params_paths]
    unknown = set(enable) - set(names)
    if unknown:
        raise GraphError(f"{path}: cannot enable {', '.join(sorted(unknown))}: not in the "
                         f"graph (nodes: {', '.join(names)})")
    nodes = [n for n in nodes if n.enabled or n.name in enable]
    if not nodes:
        raise GraphError(f"{path}: no nodes")
    _check_agreement(path, nodes, params_docs)
    profile = None
    if doc.get("dds_profile"):
        _expect(doc["dds_profile"], str, f"{path}: dds_profile", "a file name")
        profile = (path.parent / doc["dds_profile"]).resolve()
        if not profile.is_file():
            raise GraphError(f"{path}: dds_profile {profile} does not exist")
    namespace = doc.get("namespace") or ""
    _expect(namespace, str, f"{path}: namespace", "a ROS namespace such as uav1")
    return GraphSpec(nodes, params_paths, profile, normalise_namespace(namespace, path))


# a ROS name token: a letter or underscore, then letters, digits and underscores
_NAME_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def normalise_namespace(text: str, where="namespace") -> str:
    """A ROS namespace as the nodes' ``__ns`` takes it: ``uav1`` and ``/uav1/`` are
    ``/uav1``; ``""`` and ``/`` are the root, ``""``. Anything else is a GraphError."""
    tokens = text.strip().strip("/").split("/") if text.strip().strip("/") else []
    bad = [t for t in tokens if not _NAME_TOKEN.match(t)]
    if bad:
        raise GraphError(f"{where}: {text!r} is no ROS namespace ({bad[0]!r}: names are "
                         "letters, digits and underscores, not starting with a digit)")
    return "".join(f"/{t}" for t in tokens)


def namespaced_params_files(params_files, namespace: str, out_dir: Path) -> list[Path]:
    """The params files with each node's block keyed by its full name in ``namespace``,
    written to ``out_dir`` (the files themselves without a namespace).

    ROS matches a block to the node's fully qualified name: ``ekf:`` does not reach
    ``/uav1/ekf``, whose parameters would silently stay at their defaults. Wildcard blocks
    (``/**``) match anywhere and are kept as they are.
    """
    if not namespace:
        return [Path(p) for p in params_files]
    rewritten = []
    for path in map(Path, params_files):
        doc = yaml.safe_load(path.read_text()) or {}
        blocks = {key if str(key).startswith("/*") else f"{namespace}/{str(key).strip('/')}":
                  value for key, value in doc.items()}
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        target = Path(out_dir) / f"{path.stem}{namespace.replace('/', '.')}{path.suffix}"
        target.write_text(yaml.safe_dump(blocks, sort_keys=False))
        rewritten.append(target)
    return rewritten


_NODE_KEYS = {"name": str, "executable": str, "required": bool, "enabled": bool,
              "respawn": bool, "parameters": dict, "remappings": dict}


def _node_spec(path: Path, entry) -> NodeSpec:
    """One ``nodes:`` entry, every key of its type."""
    _expect(entry, dict, f"{path}: node entry {entry!r}", "a mapping with a name")
    name = entry.get("name")
    unknown = set(entry) - set(_NODE_KEYS)
    if unknown:
        raise GraphError(f"{path}: node entry {name} has unknown keys {unknown}")
    for key, kind in _NODE_KEYS.items():
        if key in entry and entry[key] is not None:
            _expect(entry[key], kind, f"{path}: node {name}: {key} {entry[key]!r}",
                    {bool: "true or false (unquoted)", str: "a string",
                     dict: "a mapping"}[kind])
    if not isinstance(name, str) or not _NAME_TOKEN.match(name):
        raise GraphError(f"{path}: node entry {entry!r}: name must be a ROS node name "
                         "(letters, digits, underscores; not starting with a digit)")
    spec = NodeSpec(name=name, executable=entry.get("executable") or name,
                    required=entry.get("required", True), enabled=entry.get("enabled", True),
                    respawn=entry.get("respawn", False),
                    parameters=dict(entry.get("parameters") or {}),
                    remappings={str(k): str(v) for k, v in
                                (entry.get("remappings") or {}).items()})
    if spec.executable not in NODES:
        raise GraphError(f"{path}: node {spec.name}: unknown executable {spec.executable} "
                         f"(known: {', '.join(sorted(NODES))})")
    return spec


def _check_params_file(path: Path, node_names: set) -> dict:
    """A ROS 2 parameters file whose blocks are all for a node (of the graph, or one this
    package has), with no key given twice: a misspelt block would leave its node on the
    defaults, a repeated key would silently replace the first, and the node would start.
    Returns the file's blocks."""
    try:
        doc = yaml.load(path.read_text(), Loader=_UniqueKeyLoader) or {}
    except (OSError, yaml.YAMLError) as err:
        raise GraphError(f"cannot read params file {path}: {err}") from err
    _expect(doc, dict, f"{path}: the top level", "a mapping of node names")
    for block in doc:
        name = str(block).strip("/")
        if block != "/**" and name not in node_names:
            raise GraphError(f"{path}: parameters for {block!r}, which names no node "
                             f"(nodes: {', '.join(sorted(node_names))}); a misspelling?")
    return doc


# Parameters that several nodes take and that must be one value: (executable, its default)
# per node. Each node converts with its own copy, and a mismatch is no error any node could
# see: the ENU origin (the ekf's GNSS and /nav/fix against the metamap's tiles, which every
# fix is in; NaN = the ekf takes the metamap's) and the geoid height (the metamap's DEM
# heights made ellipsoidal, the bridge's altitude_msl_m made from them again).
_AGREEING = {
    ("origin_latitude", "origin_longitude", "origin_altitude"):
        {"metamap": (math.nan, math.nan, 0.0), "ekf": (math.nan, math.nan, 0.0)},
    ("geoid_undulation",): {"metamap": (0.0,), "autopilot_bridge": (0.0,)},
}


def _check_agreement(path: Path, nodes: list[NodeSpec], params_docs: list[dict]):
    """Refuse a graph whose nodes would run with different values of a parameter they must
    share (:data:`_AGREEING`): as given in the params files' blocks ``params_docs`` (a
    node's block, ``/**``), then its ``parameters`` in the graph file, else its default.
    Values with a NaN are not compared: the ekf's origin is then the metamap's, the
    metamap's its DEM's centre."""
    given = {node.name: _given_parameters(node, params_docs) for node in nodes}
    for keys, defaults in _AGREEING.items():
        seen = {}
        for node in nodes:
            if node.executable not in defaults:
                continue
            values = tuple(given[node.name].get(k, d) for k, d in
                           zip(keys, defaults[node.executable], strict=True))
            if all(isinstance(v, int | float) and math.isfinite(v) for v in values):
                seen[node.name] = values
        if len({tuple(round(float(v), 9) for v in vals) for vals in seen.values()}) > 1:
            found = "; ".join(f"{name} {', '.join(f'{v:g}' for v in vals)}"
                              for name, vals in seen.items())
            raise GraphError(f"{path}: {', '.join(keys)} must be the same for every node "
                             f"that takes them, but {found}: set them once, alike")


def _given_parameters(node: NodeSpec, params_docs: list[dict]) -> dict:
    """The parameters ``node`` is given: its blocks of the params files (``/**``, then its
    own), then its ``parameters`` in the graph file."""
    given = {}
    for doc in params_docs:
        for block in ("/**", node.name, f"/{node.name}"):
            entries = doc.get(block)
            entries = entries.get("ros__parameters") if isinstance(entries, dict) else None
            given.update(entries if isinstance(entries, dict) else {})
    given.update(node.parameters)
    return given


def _expect(value, kind: type, what: str, expected: str):
    # (bool is an int in Python, and 1 is no boolean here)
    if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
        raise GraphError(f"{what} must be {expected}, not {type(value).__name__}")


class _UniqueKeyLoader(yaml.SafeLoader):
    """A YAML loader that refuses a key given twice in one mapping (the second would silently
    replace the first: a node list, a parameter)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


def _yaml_scalar(value) -> str:
    """A parameter value as ``-p name:=value`` text (YAML, so strings are quoted)."""
    return yaml.safe_dump(value, default_flow_style=True, width=1 << 20).strip().removesuffix(
        "\n...").removesuffix("...").strip()


def node_command(spec: NodeSpec, params_files=(), extra_parameters: dict | None = None,
                 namespace: str = "") -> list[str]:
    """The command line that starts one node with its parameters and remappings, in
    ``namespace`` (normalised; its params files rewritten for it) with ``/tf`` in it."""
    script = Path(sys.executable).parent / spec.executable
    if script.exists():
        cmd = [str(script)]
    elif shutil.which(spec.executable):
        cmd = [shutil.which(spec.executable)]
    else:
        module, function = NODES[spec.executable].split(":")
        cmd = [sys.executable, "-c", f"import sys; from {module} import {function}; "
               f"sys.exit({function}())"]
    cmd += ["--ros-args", "-r", f"__node:={spec.name}"]
    if namespace:
        cmd += ["-r", f"__ns:={namespace}"]
        cmd += [arg for source, target in TF_REMAPPINGS.items()
                for arg in ("-r", f"{source}:={target}")]
    for params_file in params_files:
        cmd += ["--params-file", str(params_file)]
    for key, value in {**spec.parameters, **(extra_parameters or {})}.items():
        cmd += ["-p", f"{key}:={_yaml_scalar(value)}"]
    for source, target in spec.remappings.items():
        cmd += ["-r", f"{source}:={target}"]
    return cmd


def _describe_exit(code: int) -> str:
    """'signal SIGSEGV' for a negative return code, else 'exit code N'."""
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


class GraphRunner:
    """Start, watch and stop the processes of a graph.

    Parameters
    ----------
    spec : GraphSpec
        The nodes to run.
    extra_parameters : dict, optional
        Parameters given to every node (e.g. ``{"use_sim_time": True}``).
    log_dir : Path, optional
        Also write each node's output to ``<log_dir>/<name>.log``.
    grace : float
        Seconds between SIGINT and SIGTERM, and between SIGTERM and SIGKILL, at shutdown.
    out : file
        Where the prefixed node output and the runner's reports go.
    echo : callable(name, line) -> bool, optional
        Which node output lines to copy to ``out`` (default all; the log files get all).
    """

    def __init__(self, spec: GraphSpec, extra_parameters: dict | None = None,
                 log_dir: Path | None = None, grace: float = 5.0, out=None, echo=None):
        self.spec = spec
        self.extra_parameters = extra_parameters or {}
        self.log_dir = Path(log_dir) if log_dir else None
        self.grace = grace
        self.out = out or sys.stdout
        self.echo = echo or (lambda _name, _line: True)
        self.procs: dict[str, subprocess.Popen] = {}
        self.usage: dict[str, dict] = {}
        self.exit_codes: dict[str, int] = {}
        self.died: list[str] = []
        self.respawns: Counter = Counter()   # restarts per node
        self._deaths: dict[str, deque] = {}   # when each respawned node died (monotonic)
        self._respawn_at: dict[str, float] = {}   # nodes waiting to be started again
        self._up = False   # past start-up: nodes that die from now on may be respawned
        self.run_dir: Path | None = None   # the folder the nodes share ($TERRAIN_NAV_RUN_DIR)
        self.params_files: list[Path] = []   # the spec's, rewritten for its namespace
        self._own_run_dir = False
        self._pumps: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()

    def report(self, text: str) -> None:
        with self._lock:
            print(f"[graph] {text}", file=self.out, flush=True)

    # -- start ---------------------------------------------------------------------------------
    def start(self) -> None:
        """Start every node's process."""
        if self.log_dir:
            self.log_dir.mkdir(parents=True, exist_ok=True)
        given = os.environ.get(RUN_DIR_VARIABLE) or self.log_dir
        self._own_run_dir = not given
        self.run_dir = Path(given or tempfile.mkdtemp(prefix="terrain_nav_run_"))
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.params_files = namespaced_params_files(self.spec.params_files,
                                                    self.spec.namespace, self.run_dir)
        for spec in self.spec.nodes:
            self._launch(spec)

    def _launch(self, spec: NodeSpec) -> None:
        cmd = node_command(spec, self.params_files, self.extra_parameters,
                           self.spec.namespace)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, text=True, bufsize=1,
                                env={**self.spec.environment(),
                                     RUN_DIR_VARIABLE: str(self.run_dir),
                                     SUPERVISOR_VARIABLE: str(os.getpid())},
                                start_new_session=True)
        self.procs[spec.name] = proc
        # a log file per node, appended to by its later lives
        pump = threading.Thread(target=self._pump, args=(spec.name, proc, spec.name in
                                                         self.respawns), daemon=True)
        pump.start()
        self._pumps.append(pump)
        self.report(f"started {spec.name} (pid {proc.pid})")

    def _pump(self, name: str, proc: subprocess.Popen, append: bool = False) -> None:
        log = open(self.log_dir / f"{name}.log", "a" if append else "w") \
            if self.log_dir else None  # noqa: SIM115
        try:
            for line in proc.stdout:
                if self.echo(name, line):
                    with self._lock:
                        self.out.write(f"[{name}] {line}")
                        self.out.flush()
                if log:
                    log.write(line)
        finally:
            if log:
                log.close()

    def wait_until_up(self, timeout: float = 30.0) -> float:
        """Block until every node is visible in the ROS graph; return the time it took.

        Raises GraphError if a node dies first or the timeout passes.
        """
        import rclpy

        start = time.monotonic()
        context = rclpy.Context()
        rclpy.init(context=context)
        probe = rclpy.create_node("_terrain_nav_graph_probe", context=context)
        try:
            namespace = self.spec.namespace or "/"
            wanted = {n.name for n in self.spec.nodes}
            while time.monotonic() - start < timeout:
                if self._stop.is_set():
                    raise GraphError("stopped during start-up")
                self._check_exits()
                if self.died:
                    raise GraphError(f"node(s) died during start-up: {', '.join(self.died)}")
                seen = {name for name, ns in probe.get_node_names_and_namespaces()
                        if ns == namespace}
                # Nodes that already finished normally (e.g. a short bag) count as up.
                if wanted <= seen | set(self.exit_codes):
                    elapsed = time.monotonic() - start
                    self.report(f"all {len(wanted)} nodes up in {elapsed:.1f} s")
                    self._up = True
                    return elapsed
                time.sleep(0.1)
            missing = wanted - seen
            raise GraphError(f"nodes not up after {timeout:.0f} s: {', '.join(sorted(missing))}")
        finally:
            probe.destroy_node()
            context.try_shutdown()

    # -- watch ---------------------------------------------------------------------------------
    def _check_exits(self) -> None:
        for name, proc in self.procs.items():
            if name in self.exit_codes or proc.poll() is None:
                continue
            code = proc.returncode
            self.exit_codes[name] = code
            if code == 0:
                self.report(f"{name} finished (exit code 0)")
            elif self._may_respawn(name):
                self._respawn_at[name] = time.monotonic() + RESPAWN_DELAY
                self.report(f"NODE DIED: {name} ({_describe_exit(code)}); respawning it in "
                            f"{RESPAWN_DELAY:g} s")
            else:
                self.report(f"NODE DIED: {name} ({_describe_exit(code)})")
                self.died.append(name)

    def _may_respawn(self, name: str) -> bool:
        """Whether a node that just died is to be started again (and count its death)."""
        spec = next(n for n in self.spec.nodes if n.name == name)
        if not (spec.respawn and self._up) or self._stop.is_set():
            return False
        now = time.monotonic()
        deaths = self._deaths.setdefault(name, deque())
        deaths.append(now)
        while deaths and deaths[0] < now - RESPAWN_WINDOW:
            deaths.popleft()
        if len(deaths) >= RESPAWN_LIMIT:
            self.report(f"{name} died {len(deaths)} times within {RESPAWN_WINDOW:g} s: "
                        "not respawning it again")
            return False
        return True

    def _respawn_due(self) -> None:
        """Start again the nodes whose respawn delay has passed."""
        for name, at in list(self._respawn_at.items()):
            if time.monotonic() < at or self._stop.is_set():
                continue
            del self._respawn_at[name]
            self._bank_usage(name)
            self.exit_codes.pop(name, None)
            self.respawns[name] += 1
            self._launch(next(n for n in self.spec.nodes if n.name == name))

    def sample_usage(self) -> None:
        """Record CPU time and peak resident memory of every live node (psutil)."""
        import psutil

        for name, proc in self.procs.items():
            if proc.poll() is not None:
                continue
            try:
                p = psutil.Process(proc.pid)
                cpu = p.cpu_times()
                rss = p.memory_info().rss
                created = p.create_time()
            except psutil.Error:
                continue
            # wall time from the process's own start (epoch clock, as psutil's): CPU spent
            # before the first sample over the time since the first sample gave shares in
            # the millions of percent when a graph stopped at once (issue 22)
            entry = self.usage.setdefault(name, {"cpu_s": 0.0, "peak_rss_mb": 0.0,
                                                 "started": created})
            entry["cpu_s"] = entry.get("cpu_before", 0.0) + cpu.user + cpu.system
            entry["peak_rss_mb"] = max(entry["peak_rss_mb"], rss / 2**20)
            entry["last"] = time.time()

    def _bank_usage(self, name: str) -> None:
        """Keep a dead process's CPU time (as last sampled) in its node's total."""
        entry = self.usage.get(name)
        if entry:
            entry["cpu_before"] = entry["cpu_s"]

    def spin(self, duration: float | None = None, until_exit: str | None = None) -> int:
        """Watch the processes until a stop condition; return the graph's exit status.

        Stops when a required node dies (status 1), when ``until_exit`` names a node that has
        exited, after ``duration`` seconds, when every process has ended, or on
        :meth:`request_stop` (from a signal handler).
        """
        start = time.monotonic()
        status = 0
        next_sample = start
        while not self._stop.is_set():
            if time.monotonic() >= next_sample:
                self.sample_usage()
                next_sample += 1.0
            self._check_exits()
            self._respawn_due()
            required_dead = [n.name for n in self.spec.nodes if n.required and n.name in self.died]
            if required_dead:
                self.report(f"stopping the graph: required node(s) {required_dead} died")
                status = 1
                break
            if until_exit and until_exit in self.exit_codes:
                break
            if len(self.exit_codes) == len(self.procs) and not self._respawn_at:
                break
            if duration is not None and time.monotonic() - start >= duration:
                break
            self._stop.wait(0.1)
        return status

    def request_stop(self, *_args) -> None:
        self._stop.set()

    # -- stop ----------------------------------------------------------------------------------
    def shutdown(self) -> dict[str, int]:
        """SIGINT every live node, escalate to SIGTERM then SIGKILL; return exit codes."""
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            live = {n: p for n, p in self.procs.items() if p.poll() is None}
            if not live:
                break
            for proc in live.values():
                try:
                    os.killpg(proc.pid, sig)  # the node and anything it started
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + self.grace
            while time.monotonic() < deadline and any(p.poll() is None for p in live.values()):
                time.sleep(0.05)
            if sig != signal.SIGINT and live:
                self.report(f"sent {sig.name} to {', '.join(live)}")
        for pump in self._pumps:
            pump.join(timeout=2)
        for name, proc in self.procs.items():
            self.exit_codes.setdefault(name, proc.returncode)
        if self._own_run_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)
        failed = {n: c for n, c in self.exit_codes.items() if c}
        self.report("graph stopped" + ("; non-zero exit codes: " + ", ".join(
            f"{n} {_describe_exit(c)}" for n, c in failed.items()) if failed else ""))
        return dict(self.exit_codes)


def run_graph(spec: GraphSpec, *, extra_parameters: dict | None = None,
              duration: float | None = None, until_exit: str | None = None,
              log_dir: Path | None = None, startup_timeout: float = 30.0) -> int:
    """Run a graph in the foreground, handling SIGINT/SIGTERM; return an exit status."""
    runner = GraphRunner(spec, extra_parameters, log_dir)
    previous = {s: signal.signal(s, runner.request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        runner.start()
        try:
            runner.wait_until_up(startup_timeout)
        except GraphError as err:
            runner.report(str(err))
            return 1
        return runner.spin(duration, until_exit)
    finally:
        runner.shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
