"""Ray, as mi-gaussians uses it: importing it (one line naming the extra when it is missing), joining or starting a
cluster, checking that every node sees a folder, and setting up a worker (the Mitsuba variant, Dr.Jit's threads)."""

from __future__ import annotations

import contextlib
import os
import re
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path

#: How to install what this module needs.
EXTRA = "pip install 'mi-gaussians[ray]' (in the source tree: pip install '.[ray]')"


@dataclass(frozen=True)
class Waits:
    """The longest waits on a cluster (seconds): every one is bounded and, when it runs out, says what it waited for.
    ``mi-gs sweep --connect-timeout / --check-timeout / --stop-timeout`` set them."""

    connect: float = 30.0         # the head of a cluster (--address HOST:PORT) to accept a connection
    shared_folder: float = 120.0  # every node to answer the check that it sees the output folder
    stop: float = 60.0            # the running runs, after a stop signal, to finish their iteration and checkpoint

    def __post_init__(self):
        for name in ("connect", "shared_folder", "stop"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float("inf"):
                raise ValueError(f"waits.{name}: expected a positive number of seconds, got {v!r}")


def check_reachable(address: str, seconds: float = Waits.connect) -> None:
    """Something accepts connections at ``address`` (``HOST:PORT``, ``[IPv6]:PORT``; ``auto``, ``local`` and ``ray://``
    URLs are left to Ray) within ``seconds``: ValueError with one line naming the address otherwise. Ray itself keeps retrying
    an address where nothing listens for many minutes, printing only its own warnings."""
    import socket

    if address in ("auto", "local") or "://" in address:
        return
    host, sep, port = address.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--address {address}: expected HOST:PORT (the head node's address, e.g. 10.0.0.1:6379), "
                         "or auto")
    try:
        socket.create_connection((host, int(port)), timeout=seconds).close()
    except socket.timeout:
        raise ValueError(f"--address {address}: no answer within {seconds:g} s (--connect-timeout); is the cluster's "
                         "head running there (ray start --head) and reachable from this machine?") from None
    except OSError as e:
        why = e.strerror or type(e).__name__
        raise ValueError(f"--address {address}: nothing answers there ({why}); start the cluster's head there "
                         "(ray start --head) or give its address") from None


def check_resources(ray, cpus: float, gpus: float, where: str) -> None:
    """Some alive node of the cluster has ``cpus`` CPUs and ``gpus`` GPUs for one run (both on the same node):
    ValueError with one line (``where``: the spec, as ``spec.toml: resources``) otherwise, as Ray would keep such a
    task waiting for ever."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    if any(float(r.get("CPU", 0.0)) >= cpus and float(r.get("GPU", 0.0)) >= gpus for r in nodes):
        return
    count = f"{len(nodes)} node{'s' if len(nodes) != 1 else ''}"
    for key, need, name in (("cpus", cpus, "CPU"), ("gpus", gpus, "GPU")):
        have = max((float(r.get(name, 0.0)) for r in nodes), default=0.0)
        if need > have:
            largest = f"the largest node has {have:g}" if have else f"no node of the cluster has a {name}"
            raise ValueError(f"{where}.{key}: {need:g} per run, but {largest} ({count}); lower it or add nodes")
    raise ValueError(f"{where}: {cpus:g} CPUs and {gpus:g} GPUs per run, but no node has both ({count}: "
                     + ", ".join(f"{float(r.get('CPU', 0)):g} CPUs / {float(r.get('GPU', 0)):g} GPUs" for r in nodes)
                     + "); lower them or add nodes")


def import_ray():
    """The ``ray`` module, or ValueError with one line saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ValueError(f"this needs Ray, which is not installed: {EXTRA}") from None
    return ray


@contextlib.contextmanager
def connected(address: str | None = None, num_cpus: int | None = None, connect_seconds: float = Waits.connect):
    """Join the Ray cluster at ``address``, or start a local one (``num_cpus``: its CPUs, default all); yields the
    ``ray`` module and disconnects (stopping a local cluster this started) on every path. A driver already
    connected (e.g. a test's cluster) is used as it is and left connected."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    if address:
        check_reachable(address, connect_seconds)         # (Ray itself retries an address for many minutes)
    kwargs = dict(include_dashboard=False, log_to_driver=False, logging_level="ERROR", configure_logging=True)
    try:
        if address:
            ray.init(address=address, **kwargs)
        else:
            ray.init(num_cpus=num_cpus, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = f"--address {address}: cannot join the Ray cluster there" if address else "cannot start Ray"
        hint = ""
        if address and isinstance(e, ConnectionError) and os.environ.get("RAY_AUTH_MODE", "") != "token":
            hint = ("; if the cluster uses token authentication (`ray start`'s default in recent Ray versions), set "
                    "RAY_AUTH_MODE=token here and give its token (~/.ray/auth_token or RAY_AUTH_TOKEN)")
        raise ValueError(f"{where} ({' '.join(str(e).split())[:200]}){hint}") from None
    with cluster_messages_to_stderr(ray):
        try:
            yield ray
        finally:
            ray.shutdown()                          # (its messages while it stops: still ours)


_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
_LOG_TAIL = re.compile(r"\s*Last \d+ lines of the \w+ logs:\s*$")     # (the lines we leave out)


#: What we say for Ray's messages about a node's death (a raylet's end, a task failed with its node, retried)
NODE_DIED = ("a node of the cluster died (its raylet ended); Ray runs what it held again on the other nodes, and "
             "those runs resume from their checkpoints")


# (Ray 2.60's words for it: the raylet's own end, the GCS's verdict on missed heartbeats, each lost task's retry)
_NODE_DIED_WORDS = ("Raylet is terminated", "has been marked dead", "node it was running on is dead")


def cluster_message_line(lines) -> str:
    """One line for a message the cluster pushes to its drivers (``lines``: Ray's, e.g. a raylet's death with
    the last lines of its log, its state dumps): ours for a node's death (:data:`NODE_DIED`; Ray sends two or three
    messages for one: the raylet's end, the GCS's verdict, each task's retry), else the first line that says
    something, without colour codes."""
    for text in lines:
        for line in str(text).splitlines():
            line = _LOG_TAIL.sub("", " ".join(_ANSI.sub("", line).split()))
            if line and not line.startswith("[state-dump]"):
                if any(words in line for words in _NODE_DIED_WORDS):
                    return NODE_DIED
                return line
    return ""


@contextlib.contextmanager
def cluster_messages_to_stderr(ray, quiet_seconds: float = 120.0):
    """While the block runs, the messages Ray's driver prints for the cluster (a thread of ``ray.init`` writes them
    to stdout with colour codes, a raylet's death with 20 lines of its state dumps; ``log_to_driver`` does not turn
    it off) go to stderr as one line each, once: ``ray: <what it said>`` (for a dead node, the runs' rows then say
    what it meant for them; a second death after ``quiet_seconds`` is said again). A multi-line report (an OOM kill's)
    keeps its first line. Other output of Ray's printer is left as it is. Ray without that printer
    (``ray._private.worker.print_to_stdstream``, Ray 2.x): nothing changes."""
    worker = getattr(getattr(ray, "_private", None), "worker", None)
    original = getattr(worker, "print_to_stdstream", None)
    if original is None:
        yield
        return
    said: dict[str, float] = {}        # line -> when it was last said (Ray's messages of one death come ~15 s apart)

    def printer(data, *args, **kwargs):
        import time

        if not (isinstance(data, dict) and data.get("pid") == "raylet"):
            return original(data, *args, **kwargs)
        line = cluster_message_line(data.get("lines") or [])
        now = time.monotonic()
        if line and now - said.get(line, -float("inf")) > quiet_seconds:
            said[line] = now
            from tqdm import tqdm

            tqdm.write(f"ray: {line}", file=sys.stderr)     # (on a line of its own, under a progress bar too)

    worker.print_to_stdstream = printer
    try:
        yield
    finally:
        worker.print_to_stdstream = original


def cluster_cpus(ray) -> int:
    return int(ray.cluster_resources().get("CPU", 0))


def _sees(path: str, token: str) -> tuple[bool, str]:
    """On a node: whether the file ``path`` holds ``token`` (the driver wrote it), and the node's host name."""
    import socket

    try:
        return Path(path).read_text() == token, socket.gethostname()
    except OSError:
        return False, socket.gethostname()


def check_shared_folder(ray, folder: Path, seconds: float = Waits.shared_folder) -> None:
    """Every alive node of the cluster sees ``folder`` (the same file system as this driver): ValueError with one
    line naming the nodes that do not (or do not answer within ``seconds``)."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    folder = Path(folder).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    token_file = folder / f".mi-gs-cluster-check-{uuid.uuid4().hex}"
    token = uuid.uuid4().hex
    token_file.write_text(token)
    try:
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        sees = ray.remote(num_cpus=0, max_retries=0)(_sees)
        refs = {n["NodeManagerAddress"]: sees.options(scheduling_strategy=NodeAffinitySchedulingStrategy(
            n["NodeID"], soft=False)).remote(str(token_file), token) for n in nodes}
        ready, _ = ray.wait(list(refs.values()), num_returns=len(refs), timeout=seconds)
        blind = []
        for address, ref in refs.items():
            if ref not in ready:
                blind.append(f"{address} (no answer in {seconds:g} s; --check-timeout)")
                continue
            try:
                ok, host = ray.get(ref)
            except Exception as e:                          # (e.g. mi-gaussians is not installed on that node)
                blind.append(f"{address} ({type(e).__name__})")
                continue
            if not ok:
                blind.append(f"{host} ({address})")
    finally:
        with contextlib.suppress(OSError):
            token_file.unlink()
    if blind:
        raise ValueError(f"{folder}: not seen by {len(blind)} of the cluster's {len(nodes)} nodes: "
                         f"{', '.join(blind)}; the output folder must be on a file system every node mounts at the "
                         "same path")


def setup_worker(variant: str) -> int:
    """In a Ray task or actor: select the Mitsuba ``variant`` and give Dr.Jit as many threads as the task has CPUs;
    returns that number."""
    import drjit as dr
    import mitsuba as mi

    import ray

    if mi.variant() != variant:
        mi.set_variant(variant)        # (importing this package installed the plugins for every variant)

    cpus = ray.get_runtime_context().get_assigned_resources().get("CPU", 1.0)
    threads = max(1, int(round(cpus)))
    if variant.startswith("llvm"):
        dr.set_thread_count(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    return threads


def task_error_line(e) -> str:
    """The one-line message of the exception a Ray task raised (``RayTaskError`` wraps it with its traceback)."""
    cause = getattr(e, "cause", None) or e
    lines = [ln.strip() for ln in str(cause).splitlines() if ln.strip()]
    text = " ".join(lines[:3]) if lines else type(cause).__name__
    return text if isinstance(cause, (ValueError, OSError)) else f"{type(cause).__name__}: {text}"
