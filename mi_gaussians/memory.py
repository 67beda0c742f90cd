"""Memory needs, checked before anything is allocated: an image (or a set of training images) whose buffers would not
fit in the memory this process can have is refused in one line with the estimate, instead of a machine that swaps for
minutes, a process the kernel kills without a word, or a segmentation fault under a memory limit.

The estimates are lower bounds from measured per-pixel costs (llvm_ad_rgb: a render and its NumPy copy take 90 to
115 bytes per pixel from 1 to 16 megapixels; three 1024x1024 training views 440 bytes per pixel more than three of
256x256). What the process can have: the least of the memory the system has available (``MemAvailable`` of
``/proc/meminfo``, else ``os.sysconf``), what a cgroup's ``memory.max`` leaves and what ``ulimit -v`` (RLIMIT_AS)
leaves; on a CUDA variant, the device's memory (the CUDA driver's ``cuDeviceTotalMem``).

    check_image(width, height, "cam.json")             # one rendered image (ValueError when it cannot fit)
    check_training([cams...], "DS")                    # the decoded training images and one training iteration
"""

from __future__ import annotations

import os

#: a render (the rasterizer's per-pixel buffers: colour, alpha, depth, transmittance, counts) and its NumPy copy
RENDER_BYTES_PER_PIXEL = 96
#: one training iteration on top of the render: the loss and SSIM maps, the backward pass's per-pixel state
TRAIN_STEP_BYTES_PER_PIXEL = 320
#: a training image kept decoded for the whole run (float32 RGB)
TARGET_BYTES_PER_PIXEL = 12


def _gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB" if n >= 2**30 / 10 else f"{n / 2**20:,.0f} MiB"


def _meminfo(key: str) -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                name, _, rest = line.partition(":")
                if name == key:
                    return int(rest.split()[0]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_room() -> int | None:
    """What the cgroup (v2) of this process may still use: ``memory.max`` - ``memory.current``; None without a
    limit."""
    try:
        with open("/proc/self/cgroup") as f:
            rel = next((ln.strip().split("::", 1)[1] for ln in f if ln.startswith("0::")), None)
        if rel is None:
            return None
        folder = os.path.join("/sys/fs/cgroup", rel.lstrip("/"))
        with open(os.path.join(folder, "memory.max")) as f:
            limit = f.read().strip()
        if limit == "max":
            return None
        with open(os.path.join(folder, "memory.current")) as f:
            current = int(f.read().strip())
        return max(int(limit) - current, 0)
    except (OSError, ValueError, StopIteration):
        return None


def _address_space_room() -> int | None:
    """What ``ulimit -v`` (RLIMIT_AS) leaves this process: the limit minus its mapped size; None without a limit."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft == resource.RLIM_INFINITY or soft < 0:
            return None
        with open("/proc/self/status") as f:
            size = next(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmSize:"))
        return max(soft - size, 0)
    except (OSError, ValueError, StopIteration, ImportError):
        return None


def host_available() -> tuple[int, str] | None:
    """(bytes, where that number comes from): the memory this process can still have on the host; None when the
    system does not say."""
    found = []
    avail = _meminfo("MemAvailable")
    if avail is not None:
        found.append((avail, "available (MemAvailable, /proc/meminfo)"))
    else:
        try:
            found.append((os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "free (os.sysconf)"))
        except (ValueError, OSError, AttributeError):
            pass
    room = _cgroup_room()
    if room is not None:
        found.append((room, "left under its cgroup's memory.max"))
    room = _address_space_room()
    if room is not None:
        found.append((room, "left under ulimit -v (RLIMIT_AS)"))
    return min(found) if found else None


def device_total() -> int | None:
    """The memory of CUDA device 0 (bytes), from the CUDA driver; None when there is none or it does not answer."""
    import ctypes

    try:
        cuda = ctypes.CDLL("libcuda.so.1")
        dev, total = ctypes.c_int(), ctypes.c_size_t()
        if cuda.cuInit(0) != 0 or cuda.cuDeviceGet(ctypes.byref(dev), 0) != 0:
            return None
        if cuda.cuDeviceTotalMem_v2(ctypes.byref(total), dev) != 0:
            return None
        return int(total.value)
    except (OSError, AttributeError):
        return None


def _on_device() -> bool:
    try:
        import mitsuba as mi

        return bool(mi.variant()) and mi.variant().startswith("cuda")
    except (ImportError, AttributeError, TypeError):
        return False


def available() -> tuple[int, str] | None:
    """(bytes, what they are) that buffers of the current Mitsuba variant can take: the CUDA device's memory on a
    cuda variant (when the driver says), else :func:`host_available`."""
    if _on_device():
        total = device_total()
        if total is not None:
            return total, "of memory on the CUDA device"
    found = host_available()
    return None if found is None else (found[0], f"{found[1]} on this machine")


def check(need: int, what: str, detail: str, advice: str) -> None:
    """ValueError (one line: ``what``, the estimate ``need`` and what it is for (``detail``), what there is, and
    ``advice``) when ``need`` bytes exceed what the buffers can take; nothing when they fit or nobody says."""
    have = available()
    if have is None or need <= have[0]:
        return
    raise ValueError(f"{what}: {detail} need about {_gib(need)} of memory, more than the {_gib(have[0])} {have[1]}; "
                     f"{advice}")


def check_image(width: int, height: int, what: str, advice: str = "use a smaller image size") -> None:
    """One rendered image of ``width`` x ``height`` pixels (:data:`RENDER_BYTES_PER_PIXEL`)."""
    need = int(width) * int(height) * RENDER_BYTES_PER_PIXEL
    check(need, what, f"the buffers of a {int(width):,}x{int(height):,} image ({RENDER_BYTES_PER_PIXEL} bytes per "
                      "pixel)", advice)


def training_need(sizes) -> int:
    """Bytes a run on training images of ``sizes`` ((width, height) each) needs at least: every image decoded
    (:data:`TARGET_BYTES_PER_PIXEL`) and one iteration on the largest (:data:`RENDER_BYTES_PER_PIXEL` +
    :data:`TRAIN_STEP_BYTES_PER_PIXEL`)."""
    pixels = [int(w) * int(h) for w, h in sizes]
    if not pixels:
        return 0
    return sum(pixels) * TARGET_BYTES_PER_PIXEL + max(pixels) * (RENDER_BYTES_PER_PIXEL + TRAIN_STEP_BYTES_PER_PIXEL)


def check_training(sizes, what: str, advice: str) -> None:
    """A run on training images of ``sizes`` ((width, height) each; :func:`training_need`)."""
    sizes = list(sizes)
    w, h = max(sizes, key=lambda s: s[0] * s[1])
    check(training_need(sizes), what, f"{len(sizes):,} training images (the largest {w:,}x{h:,}) and the buffers of "
                                      "one training iteration", advice)
