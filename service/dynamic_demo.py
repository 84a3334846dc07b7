"""The chapter-6 part of ``pointfence demo``: moving surfaces, the tool's shadow, the self-filter
(simulated clock: 30 Hz synthetic frames, 1 kHz ticks; the scenarios of bench/dynamic_scenes.py).

Hook (service/demo.py, after the chapter-2 probes)::

    if not args.no_dynamic:
        from . import dynamic_demo
        dynamic_results = dynamic_demo.run(backend.name, args.device or cfg.device)
"""
from __future__ import annotations

from pointfence.bench import dynamic_scenes as ds


def _speed(v):
    return f">{ds.SPEEDS[-1]:g}" if v is None else f"{v:g}"


def run(backend: str = "opencl", device: str | None = None, latency: float = 0.1, out=print) -> dict:
    """Print the chapter-6 table and return its figures."""
    out("\nchapter 6: dynamic scene (simulated 1 kHz ticks, 30 Hz frames, 2 cm fixture)")
    res = {}
    for label, kw in (("no latency", {}), (f"camera latency {latency * 1000:.0f} ms", {"latency": latency})):
        off = ds.popthrough_speed(False, backend=backend, device=device, **kw)
        on = ds.popthrough_speed(True, backend=backend, device=device, **kw)
        res[label] = {"without_prediction": off["popthrough_mps"], "with_prediction": on["popthrough_mps"]}
        out(f"  translating plane, {label:22s}: pop-through at {_speed(off['popthrough_mps'])} m/s without "
            f"motion prediction, {_speed(on['popthrough_mps'])} m/s with it (held {on['held_mps']} m/s)")
    one, two = ds.occlusion_run(1, backend=backend, device=device), ds.occlusion_run(2, backend=backend, device=device)
    res["occlusion_penetration_mm_1cam"] = round(one.max_penetration * 1e3, 2)
    res["occlusion_penetration_mm_2cam"] = round(two.max_penetration * 1e3, 2)
    out(f"  tool's shadow over a protected disc, architecture III: penetration {res['occlusion_penetration_mm_1cam']:.2f} mm "
        f"with the top camera alone, {res['occlusion_penetration_mm_2cam']:.2f} mm with a second (side) camera")
    sf = ds.self_filter_ratio(backend=backend, device=device)
    res["self_filter"] = sf
    out(f"  robot self-filter: {sf['false_fixture_points_without']} protected points on the instrument without it, "
        f"{sf['false_fixture_points_with']} with it (ratio {sf['self_filter_false_fixture_ratio']:g}); tips fenced "
        f"in by their own tool {sf['tips_fenced_without']} -> {sf['tips_fenced_with']}")
    return res
