"""Forward + backward time and peak memory of the Gaussian rasteriser.

For every (number of Gaussians, resolution) and every available backend
(the pure-torch path on CPU; on CUDA also the torch path on the GPU and
gsplat) this measures, in a fresh subprocess per configuration:

* the median and minimum wall time of ``rasterize`` forward + backward
  (loss = sum of image + depth + alpha, gradients w.r.t. means, quats,
  scales, opacities and colours);
* the peak memory of one forward + backward: on CPU the growth of the
  process's peak resident set size (Linux ``VmHWM``, reset before the pass;
  ``getrusage`` elsewhere), on CUDA ``torch.cuda.max_memory_allocated``;
* the number of Gaussian-pixel pairs evaluated (torch path) and pairs per
  second.

Scene: Gaussians uniformly in a box 2-6 m in front of the camera that spans
the view at 6 m, scales log-uniform in 0.5-5 % of the scene size (the 4 m
depth extent of the box, i.e. 2-20 cm, per axis), random rotations,
opacities uniform in 0.1-0.9, RGB colours, 60 degree horizontal field of
view.  Torch runs with 2 intra-op threads unless told otherwise.

    splatreplace bench render --json benchmarks/results/render_cpu.json
    python benchmarks/bench_render.py --json benchmarks/results/render_cpu.json
"""

from __future__ import annotations

import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

from typing_extensions import Literal

DEFAULT_COUNTS: Tuple[int, ...] = (5000, 20000, 100000)
DEFAULT_RESOLUTIONS: Tuple[Tuple[int, int], ...] = ((128, 96), (160, 120), (320, 240))
_REPO_ROOT = Path(__file__).resolve().parents[2]
_RESULT_MARK = "BENCH_RENDER_RESULT "


@dataclass
class BenchRenderConfig:
    """Time forward + backward of the splat rasteriser per scene size and backend."""

    json: Optional[Path] = None
    """Where to write the results as JSON."""
    counts: Tuple[int, ...] = DEFAULT_COUNTS
    """Numbers of Gaussians."""
    resolutions: Tuple[Tuple[int, int], ...] = DEFAULT_RESOLUTIONS
    """Image sizes (width, height)."""
    repeats: int = 7
    """Timed forward + backward passes per configuration (after one warm-up)."""
    device: Literal["cpu", "cuda", "auto"] = "auto"
    """cpu; cuda (torch path on the GPU and gsplat); auto: cuda when available, else cpu."""
    threads: int = 2
    """Torch intra-op threads."""

    def main(self) -> Dict[str, Any]:
        return run_render_bench(
            sizes=self.resolutions,
            counts=self.counts,
            repeats=self.repeats,
            json_path=self.json,
            device=self.device,
            threads=self.threads,
        )


def main(config: Optional[BenchRenderConfig] = None) -> Dict[str, Any]:
    """Run the benchmark with ``config`` (defaults if None)."""
    return (config or BenchRenderConfig()).main()


# --------------------------------------------------------------------------- #
# scene                                                                       #
# --------------------------------------------------------------------------- #


def make_bench_scene(n: int, width: int, height: int, seed: int = 0, device: str = "cpu", fov_deg: float = 60.0):
    """The benchmark scene (see the module docstring), float32 on ``device``.

    Returns (means, quats, scales, opacities, colors, viewmat, K)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    tan_x = math.tan(math.radians(fov_deg) / 2)
    fx = 0.5 * width / tan_x
    tan_y = 0.5 * height / fx
    z_near, z_far = 2.0, 6.0
    size = z_far - z_near
    lo = torch.tensor([-z_far * tan_x, -z_far * tan_y, z_near])
    hi = torch.tensor([z_far * tan_x, z_far * tan_y, z_far])
    means = lo + (hi - lo) * torch.rand(n, 3, generator=g)
    log_s = torch.empty(n, 3).uniform_(math.log(0.005 * size), math.log(0.05 * size), generator=g)
    quats = torch.randn(n, 4, generator=g)
    opacities = 0.1 + 0.8 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    K = torch.tensor([[fx, 0.0, width / 2], [0.0, fx, height / 2], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    return tuple(t.to(device) for t in (means, quats, log_s.exp(), opacities, colors, viewmat, K))


# --------------------------------------------------------------------------- #
# one configuration (runs in its own process)                                 #
# --------------------------------------------------------------------------- #


def proc_status_mb(field: str) -> Optional[float]:
    """A memory field of /proc/self/status (VmRSS, VmHWM, ...) in MB; None where there is none."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return None


def peak_tracker():
    """(start, peak) callables measuring the growth of the resident set.

    Linux: VmHWM after resetting it through /proc/self/clear_refs (the
    getrusage maximum would include the parent's size inherited through
    fork + exec).  Elsewhere: getrusage's maximum resident set size."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        use_proc = proc_status_mb("VmHWM") is not None
    except OSError:
        use_proc = False
    if use_proc:
        base = proc_status_mb("VmRSS")
        return lambda: (proc_status_mb("VmHWM") or 0.0) - (base or 0.0)
    scale = 1 / (1024 * 1024) if sys.platform == "darwin" else 1 / 1024
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale
    return lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale - base


def measure(n: int, width: int, height: int, backend: str, device: str, repeats: int, threads: int) -> Dict[str, Any]:
    """Time ``repeats`` forward + backward passes of one configuration in this process."""
    import torch

    from splatreplace_ns.render import rasterize

    torch.set_num_threads(threads)
    cuda = device.startswith("cuda")

    def sync():
        if cuda:
            torch.cuda.synchronize()

    scene = make_bench_scene(n, width, height, device=device)
    leaves = [t.clone().requires_grad_(True) for t in scene[:5]]
    viewmat, K = scene[5], scene[6]

    def step():
        for t in leaves:
            t.grad = None
        out = rasterize(*leaves, viewmat, K, width, height, backend=backend)
        (out.image.sum() + out.depth.sum() + out.alpha.sum()).backward()
        return out

    sync()
    if cuda:
        torch.cuda.reset_peak_memory_stats()
        mem0 = torch.cuda.memory_allocated() / 2**20
    else:
        cpu_peak = peak_tracker()
    out = step()  # warm-up; also the pass whose peak memory is reported
    sync()
    peak_mb = torch.cuda.max_memory_allocated() / 2**20 - mem0 if cuda else cpu_peak()
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        step()
        sync()
        times.append(time.perf_counter() - t0)
    median = statistics.median(times)
    pairs = out.n_pairs
    return {
        "n_gaussians": n,
        "resolution": f"{width}x{height}",
        "backend": backend,
        "device": "cuda" if cuda else "cpu",
        "threads": threads,
        "median_ms": round(1000 * median, 2),
        "min_ms": round(1000 * min(times), 2),
        "peak_mem_mb": round(peak_mb, 1),
        "n_visible": int((out.radii > 0).sum()),
        "pairs": pairs,
        "pairs_backward": out.extras.get("n_pairs_backward"),
        "mpairs_per_s": round(pairs / median / 1e6, 2) if pairs else None,
        "mean_alpha": round(float(out.alpha.detach().mean()), 4),
        "times_ms": [round(1000 * t, 2) for t in times],
    }


def _run_isolated(spec: Dict[str, Any]) -> Dict[str, Any]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(_REPO_ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
    env.setdefault("OMP_NUM_THREADS", str(spec["threads"]))
    proc = subprocess.run(
        [sys.executable, "-m", "splatreplace_ns.tools.bench.render", "--worker", json.dumps(spec)],
        capture_output=True,
        text=True,
        env=env,
        cwd=str(_REPO_ROOT),
    )
    for line in proc.stdout.splitlines():
        if line.startswith(_RESULT_MARK):
            return json.loads(line[len(_RESULT_MARK) :])
    raise RuntimeError(
        f"benchmark worker failed for {spec} (exit {proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    )


# --------------------------------------------------------------------------- #
# driver                                                                      #
# --------------------------------------------------------------------------- #


def _machine_info(device: str) -> Dict[str, Any]:
    import torch

    info: Dict[str, Any] = {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
    }
    try:
        import gsplat

        info["gsplat"] = gsplat.__version__
    except Exception:  # pragma: no cover - depends on the install
        info["gsplat"] = None
    if device == "cuda":
        info["cuda_device"] = torch.cuda.get_device_name(0)
    return info


def _backends(device: str) -> List[Tuple[str, str]]:
    """(backend, device) pairs to measure; on CUDA gsplat only where its kernels load (else the reason is printed)."""
    if device == "cpu":
        return [("torch", "cpu")]
    from splatreplace_ns.render.rasterize import gsplat_unavailable_reason

    reason = gsplat_unavailable_reason()
    if reason is not None:
        print(f"gsplat rows left out: {reason}", flush=True)
        return [("torch", "cuda")]
    return [("torch", "cuda"), ("gsplat", "cuda")]


def run_render_bench(
    sizes: Sequence[Tuple[int, int]] = DEFAULT_RESOLUTIONS,
    counts: Sequence[int] = DEFAULT_COUNTS,
    repeats: int = 7,
    json_path: Optional[Path] = None,
    device: str = "auto",
    threads: int = 2,
    isolate: bool = True,
) -> Dict[str, Any]:
    """Benchmark every (count, size, backend); print a table; optionally write JSON.

    ``isolate``: run each configuration in a fresh subprocess (needed for a
    meaningful CPU peak-memory figure).  Returns the result dict."""
    import torch

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("device='cuda' requested but CUDA is not available")
    rows: List[Dict[str, Any]] = []
    header = ["n_gaussians", "resolution", "backend", "device", "median_ms", "min_ms", "peak_mem_mb",
              "pairs", "mpairs_per_s", "load_avg"]
    print(" | ".join(f"{h:>12}" for h in header), flush=True)
    for n in counts:
        for width, height in sizes:
            for backend, dev in _backends(device):
                spec = dict(n=int(n), width=int(width), height=int(height), backend=backend, device=dev,
                            repeats=int(repeats), threads=int(threads))
                load = os.getloadavg()[0]
                row = _run_isolated(spec) if isolate else measure(**spec)
                row["load_avg"] = round(load, 2)
                rows.append(row)
                print(" | ".join(f"{str(row[h]):>12}" for h in header), flush=True)
    result = {
        "benchmark": "render",
        "machine": _machine_info(device),
        "parameters": {
            "counts": list(counts),
            "resolutions": [list(s) for s in sizes],
            "repeats": repeats,
            "device": device,
            "threads": threads,
            "loss": "image.sum() + depth.sum() + alpha.sum(), backward to means/quats/scales/opacities/colors",
            "scene": "box 2-6 m spanning the view at 6 m, scales log-uniform 2-20 cm, opacity U(0.1, 0.9), "
            "60 deg horizontal fov, RGB colours",
        },
        "results": rows,
    }
    if json_path is not None:
        json_path = Path(json_path)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {json_path}")
    return result


def _worker_main(argv: List[str]) -> None:
    spec = json.loads(argv[argv.index("--worker") + 1])
    row = measure(**spec)
    print(_RESULT_MARK + json.dumps(row), flush=True)


if __name__ == "__main__":
    if "--worker" in sys.argv:
        _worker_main(sys.argv)
    else:
        import tyro

        tyro.cli(BenchRenderConfig).main()
