"""`renderer render --backend mitsuba` and `--cluster`: the renders that do not run in our own process."""
from __future__ import annotations

import sys

import torch

from camio.errors import UsageError
from renderer.tracing.render import RenderResult


MITSUBA_SAMPLER = "independent"  # the sampler Mitsuba renders with, whichever pattern the scene asks for


def render_mitsuba(scene, spp: int | None = None, sampler: str | None = None, *, seed: int = 0,
                   variant: str | None = None, progress: bool = True, ignored=()) -> RenderResult:
    """Render `scene` in Mitsuba 3 with our camera (renderer.mitsuba): `direct` integrator, one emitter
    sample, box pixel filter, Mitsuba's own `MITSUBA_SAMPLER` (`sampler`, else the scene's image.sampler,
    is named when it differs). Prints one line naming what could not be mapped, and the options in `ignored`
    (strings such as "--compile"); the result's `not_mapped` lists the same. variant: Mitsuba variant
    [llvm_ad_rgb where it runs, else scalar_rgb]. Coverage is 1 everywhere (our cameras give every pixel a ray)."""
    try:
        from renderer.mitsuba import develop, load_mitsuba, to_mitsuba
        mi = load_mitsuba(variant or "llvm_ad_rgb")
    except ImportError as e:
        raise UsageError(f"--backend mitsuba: {e}") from None
    spp = scene.image.spp if spp is None else spp
    try:
        scene_dict, dropped = to_mitsuba(scene, spp)
    except NotImplementedError as e:
        raise UsageError(f"--backend mitsuba: {e}") from None
    notes = list(dropped)
    sampler = sampler or scene.image.sampler
    if sampler != MITSUBA_SAMPLER:
        notes.append(f"sampler {sampler} (Mitsuba's {MITSUBA_SAMPLER} sampler used)")
    notes += [f"{option} ignored" for option in ignored]
    image = torch.from_numpy(develop(scene, mi.render(mi.load_dict(scene_dict), seed=seed)))
    # Said once the image is there and finite: a render the caller refuses (float32 overflow) ends with one line.
    if (progress or notes) and bool(torch.isfinite(image).all()):
        print(f"renderer: mitsuba {mi.variant()}; not mapped: {'; '.join(notes) if notes else 'nothing'}",
              file=sys.stderr)
    return RenderResult(image, torch.ones(image.shape[:2], dtype=image.dtype), tuple(notes))


def render_with(backend: str, cluster: str | None, scene, spp, sampler, *, device, seed: int,
                progress: bool, compile: bool = False, intersector: str = "auto") -> RenderResult:
    """Dispatch of `cmd_render` for --backend mitsuba and --cluster (not both). compile, intersector: the
    command line's --compile and --intersector; what a backend does not use is named on stderr."""
    if backend == "mitsuba":
        if cluster:
            raise UsageError("--cluster works with the torch backend only")
        ignored = [name for name, given in (("--compile", compile),
                                            (f"--intersector {intersector}", intersector != "auto"),
                                            (f"--device {device}", torch.device(device).type != "cpu")) if given]
        return render_mitsuba(scene, spp, sampler, seed=seed, progress=progress, ignored=ignored)
    if torch.device(device).type != "cpu":
        raise UsageError("--cluster traces on the cluster's CPUs: leave out --device")
    if compile:  # render_on_ray traces uncompiled: each Ray worker would pay its own compile (up to a minute)
        print("renderer: --compile ignored with --cluster (the workers trace uncompiled)", file=sys.stderr)
    try:
        from renderer.tracing.distributed import render_on_ray
        return render_on_ray(scene, spp, sampler, address=cluster, seed=seed, progress=progress)
    except (ImportError, ConnectionError) as e:
        raise UsageError(str(e)) from None
