"""Where a Dr.Jit workload's device time goes: ``dr.kernel_history()`` entries summed by kind, and its longest
compiled kernels (size, operations, inputs/outputs), as a Markdown table. Used by ``render.py --profile`` and
``train_speed.py --profile`` (on CUDA, what the profile says is where to look for the gap to gsplat)."""

from __future__ import annotations

from collections import defaultdict


def history_table(history: list[dict], per: int = 1, top: int = 8) -> str:
    """Kernel time by kind (JIT, sorts, reductions, memsets, copies), then the ``top`` longest JIT kernels;
    times and counts divided by ``per`` (e.g. the iterations the history covers)."""
    by_type = defaultdict(lambda: [0, 0.0])
    jit = []
    for h in history:
        t = h.get("execution_time", 0.0)
        kind = str(h["type"]).split(".")[-1]
        by_type[kind][0] += 1
        by_type[kind][1] += t
        if kind == "JIT":
            jit.append(h)
    total = sum(v[1] for v in by_type.values()) or 1.0
    lines = ["| kind | launches | ms | share |", "|---|---:|---:|---:|"]
    for kind, (n, t) in sorted(by_type.items(), key=lambda kv: -kv[1][1]):
        lines.append(f"| {kind} | {n / per:.1f} | {t / per:.3f} | {100.0 * t / total:.1f} % |")
    lines += ["", "| longest JIT kernels | ms | size | operations | inputs | outputs |", "|---|---:|---:|---:|---:|---:|"]
    merged = defaultdict(lambda: [0.0, 0, None])
    for h in jit:                       # the same kernel launched each iteration counts once, its time summed
        key = (h.get("hash"), h.get("size"))
        merged[key][0] += h.get("execution_time", 0.0)
        merged[key][1] += 1
        merged[key][2] = h
    for (hsh, size), (t, n, h) in sorted(merged.items(), key=lambda kv: -kv[1][0])[:top]:
        lines.append(f"| {str(hsh)[:8]} (x{n / per:g}) | {t / per:.3f} | {size:,} | {h.get('operation_count', 0):,} "
                     f"| {h.get('input_count', 0)} | {h.get('output_count', 0)} |")
    return "\n".join(lines)
