"""The `renderer` command.

    renderer render SCENE.json -o OUT.(exr|png|tif) [--spp N] [--sampler S] [--set key.path=value ...]
                    [--device cpu|cuda] [--seed N] [--encoding srgb|linear] [--quiet]
                    [--backend torch|mitsuba] [--cluster auto|ADDRESS]
    renderer animate SCENE.json --method beam|trace [--frames N] [--step D] -o DIR [--set key.path=value ...]
                     [--cluster auto|ADDRESS]
    renderer gallery [-o gallery.png] [--quick] [--size PX] [--spp N] [--manifest M.json] [--device ...]

Errors in the input (a bad scene file, an unreadable image, an unwritable output, a render whose float32
result overflowed) print one line `renderer: <message>` on stderr and exit with status 2, leaving no output
file behind; an interrupt (Ctrl-C, SIGTERM) prints `renderer: interrupted` and exits with 130.
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import shutil
import signal
import sys
import textwrap
import time
import warnings

from camio.errors import ImageIOError, SceneError, UsageError, one_line
from camio.interrupts import interrupt_on_sigterm
from camio.files import atomic_output, linear_to_srgb, output_problem, write_image
from camio.checks import parse_device, read_json

SCENES_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scenes")
GALLERY_MANIFEST = os.path.join(SCENES_DIR, "gallery.json")
EXIT_USAGE = 2


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    if value > MAX_COUNT:
        raise argparse.ArgumentTypeError(f"expected an integer <= {MAX_COUNT}, got {value}")
    return value


# Command-line counts (--spp, --size, --columns) share the scene file's largest limit (MAX_SPP, MAX_IMAGE_SIDE).
MAX_COUNT = 1 << 16
MAX_SEED = (1 << 63) - 1


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2^63 - 1], got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    from renderer.core.params import SAMPLERS

    parser = argparse.ArgumentParser(prog="renderer", description="Batched PyTorch ray tracer for unusual cameras "
                                     "(inverted and mixed perspective, tilted lenses).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser("render", help="render a scene file to an image",
                       description="Render a scene file. EXR keeps linear float; PNG is 8-bit sRGB, TIFF 16-bit sRGB.")
    r.add_argument("scene", metavar="SCENE", help="scene file (JSON), or the name of a shipped scene such as fig7")
    r.add_argument("-o", "--output", required=True, metavar="OUT", help="output image: .exr, .png or .tif")
    r.add_argument("--spp", type=_positive_int, help="samples per pixel [the scene's image.spp]")
    r.add_argument("--sampler", choices=SAMPLERS, help="sample pattern [the scene's image.sampler]")
    r.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scene key before validation, e.g. camera.alpha=2 or objects.2.material.color="
                        "[1,0,0] (value parsed as JSON, else a string); repeatable")
    _common(r)
    r.add_argument("--camera", metavar="CALIB",
                   help="render through a calibration (CALIB.json, OpenCV .yml/.xml or mrcal .cameramodel): the "
                        "scene's camera becomes the calibrated one, at the calibration's image size")
    r.add_argument("--view", metavar="K", help="with --camera: the view (index or image name) whose pose is used [0]")
    r.add_argument("--encoding", choices=("srgb", "linear"),
                   help="output encoding [sRGB for PNG/TIFF, linear for EXR]")
    r.add_argument("--quiet", action="store_true", help="no progress on stderr, nor torch's warnings (e.g. --compile's)")
    r.add_argument("--backend", choices=("torch", "mitsuba"), default="torch",
                   help="torch: our tracer [default]; mitsuba: export the scene to Mitsuba 3 and render it there with "
                        "our camera (the `direct` integrator; one stderr line names what cannot be mapped, the lens "
                        "distortion and sampler included, and the --compile/--intersector/--device it ignores)")
    r.add_argument("--cluster", metavar="auto|ADDRESS",
                   help="trace on a Ray cluster (auto: the running one, else a local one); same image as one process")
    r.add_argument("--intersector", choices=("auto", "torch", "mitsuba"), default="auto",
                   help="auto: mitsuba where it runs here (CPU, float32, shapes it has), else torch [default]; "
                        "torch: our ray-shape tests; mitsuba: hits and shadow rays by Embree through "
                        "Mitsuba 3 (CPU), cameras and shading still ours (for direct light and a thin lens as "
                        "Dr.Jit kernels beside Embree)")
    r.add_argument("--compile", action="store_true",
                   help="compile the tracing with torch.compile (seconds to a minute the first time, cached on "
                        "disk); with the mitsuba intersector, direct light and a thin lens, the fused stages of "
                        "renderer.tracing.fused (slower than the default Dr.Jit kernels)")

    g = sub.add_parser("gallery", help="render the paper figures into one labelled contact sheet",
                       description="Render every entry of the gallery manifest and lay them out in one PNG.")
    g.add_argument("-o", "--output", default="gallery.png", metavar="OUT", help="contact sheet [gallery.png]")
    g.add_argument("--quick", action="store_true", help="small previews: at most 128 px and 4 spp per panel")
    g.add_argument("--size", type=_positive_int, metavar="PX", help="longest side of each panel, pixels")
    g.add_argument("--spp", type=_positive_int, help="samples per pixel for every panel")
    g.add_argument("--columns", type=_positive_int, default=4, help="panels per row [4]")
    g.add_argument("--manifest", default=GALLERY_MANIFEST, metavar="M.json",
                   help="list of {scene, label, set?, note?} entries [the shipped renderer/scenes/gallery.json]")
    _common(g)

    a = sub.add_parser("animate", help="move the camera along its view direction and render each frame",
                       description="Move the camera by D along its view direction per frame; write DIR/frame_0000.png "
                                   "... and DIR/frames.csv (frame, seconds, regions, redetermined, segment_seconds).")
    a.add_argument("scene", metavar="SCENE", help="scene file (JSON), or the name of a shipped scene such as beam_fig2")
    a.add_argument("--method", choices=("beam", "trace"), default="beam",
                   help="beam: improved beam tracing (renderer.beam); trace: the ray tracer [beam]")
    a.add_argument("--frames", type=_positive_int, help="number of frames [the scene's animation.frames]")
    a.add_argument("--step", type=float, help="camera move per frame, scene units [the scene's animation.step]")
    a.add_argument("-o", "--output", required=True, metavar="DIR", help="output folder")
    a.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scene key before validation (as for render); repeatable")
    a.add_argument("--quiet", action="store_true", help="no progress on stderr")
    a.add_argument("--cluster", metavar="auto|ADDRESS",
                   help="render the frames as Ray tasks (auto: the running cluster, else a local one); same frames")
    _common(a)
    return parser


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", help="torch device: cpu or cuda [cpu]")
    p.add_argument("--seed", type=_seed, default=0, help="sampler seed, 0 to 2^63 - 1 [0]")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    previous = interrupt_on_sigterm()
    previous_int = _remember_interrupts()
    try:
        with warnings.catch_warnings(), _torch_warnings_silenced(getattr(args, "quiet", False)):
            # numpy's floating-point warnings would print before the one-line error; failures are reported once.
            warnings.simplefilter("ignore", RuntimeWarning)
            check_inputs(args)  # before torch loads (parse_device): a bad file or option is refused at once
            device = parse_device(args.device)
            if args.command == "render":
                return cmd_render(args, device)
            if args.command == "animate":
                return cmd_animate(args, device)
            return cmd_gallery(args, device)
    except (SceneError, ImageIOError, OSError, UsageError) as e:
        print(f"renderer: {one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    except MemoryError:
        print("renderer: out of memory (use a smaller image.width/height or --spp)", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("renderer: interrupted", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if previous_int is not None:
            signal.signal(signal.SIGINT, previous_int)
        from camio.interrupts import INTERRUPTS

        INTERRUPTS.clear()  # acted on: a later call in this process (tests, a library user) starts afresh


class _BelowError(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.ERROR


@contextlib.contextmanager
def _torch_warnings_silenced(quiet: bool):
    """Under --quiet, torch's own warnings (torch.compile's recompilation and graph-break notes, which came to
    32 stderr lines for one `--compile` render) are not printed: warnings raised in torch's modules are ignored
    and torch's log handlers (each torch logger has its own and does not propagate) drop records below ERROR.
    Errors still print; everything is restored afterwards."""
    if not quiet:
        yield
        return
    handlers = {h for name, lg in list(logging.root.manager.loggerDict.items())
                if name == "torch" or name.startswith("torch.") if isinstance(lg, logging.Logger)
                for h in lg.handlers}
    below_error = _BelowError()
    for h in handlers:
        h.addFilter(below_error)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", module=r"torch(\.|$)")
            yield
    finally:
        for h in handlers:
            h.removeFilter(below_error)


def _remember_interrupts():
    """SIGINT raises KeyboardInterrupt as by default and is remembered, so that one raised where a library
    drops it (a Ctrl-C to the process group while the render's worker processes started was once ignored, and
    the image written with exit 0: issue 24) still ends the command (`camio.interrupts.INTERRUPTS`: at the
    render's next wake, `_check_interrupts` before writing); returns the old handler, or None where it is not
    ours to set (not the main thread, or SIGINT ignored by our parent)."""
    from camio.interrupts import INTERRUPTS

    def handler(signum, frame):
        INTERRUPTS.append(signum)
        raise KeyboardInterrupt

    try:
        if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
            return None
        return signal.signal(signal.SIGINT, handler)
    except ValueError:  # not the main thread
        return None


def _check_interrupts() -> None:
    """Raise KeyboardInterrupt where a Ctrl-C reached this command but its exception was dropped on the way."""
    from camio.interrupts import INTERRUPTS

    if INTERRUPTS:
        raise KeyboardInterrupt


def resolve_scene(name: str) -> str:
    """A scene file as given, else the shipped scene of that name (`fig7` -> renderer/scenes/fig7.json)."""
    if os.path.exists(name) or os.sep in name:
        return name
    shipped = os.path.join(SCENES_DIR, name if name.endswith(".json") else name + ".json")
    return shipped if os.path.isfile(shipped) else name


def check_inputs(args) -> None:
    """Refuse what can be refused without torch (whose import takes seconds): the output path, options that
    need each other, a missing --camera, the scene file's or manifest's JSON (an `extends` chain included).
    The scene's fields are validated when it loads."""
    from camio.checks import read_scene_json

    if args.command == "render":
        _check_output(args.output, RENDER_EXTENSIONS)
        if args.view is not None and not args.camera:
            raise UsageError("--view: needs --camera (the calibration whose view it names)")
        if args.camera and not os.path.exists(args.camera):
            raise UsageError(f"--camera: {args.camera}: no such file")
        read_scene_json(resolve_scene(args.scene))
    elif args.command == "animate":
        read_scene_json(resolve_scene(args.scene))
        if os.path.exists(args.output) and not os.path.isdir(args.output):
            raise UsageError(f"{args.output}: not a folder")
    else:
        _check_output(args.output, (".png",))
        read_manifest(args.manifest)


RENDER_EXTENSIONS = (".exr", ".png", ".tif", ".tiff")


def cmd_render(args, device) -> int:
    from renderer.tracing.render import render
    from renderer.scene.file import load_scene, require_objects

    scene_file = resolve_scene(args.scene)
    if args.camera:
        try:
            scene = load_scene(_with_camera(scene_file, args), args.overrides,
                               base_dir=os.path.dirname(os.path.abspath(scene_file)))
        except SceneError as e:  # the camera's keys came from --camera and --view: name the options
            text = str(e)
            for key, option in (("camera.view: ", "--view: "), ("camera.file: ", "--camera: ")):
                if text.startswith(key):
                    raise SceneError(option + text[len(key):]) from None
            raise SceneError(f"{scene_file}: {text}") from None
    else:
        scene = load_scene(scene_file, args.overrides)
    require_objects(scene_file, scene)
    if args.intersector != "auto" and args.backend != "mitsuba":  # auto: the scene's own default
        from renderer.mitsuba.intersect import use_intersector

        try:
            use_intersector(scene, args.intersector, device)
        except (ValueError, NotImplementedError, ImportError) as e:
            raise UsageError(f"--intersector {args.intersector}: {one_line(e)}") from None
    start = time.perf_counter()
    if args.backend == "mitsuba" or args.cluster:
        from renderer.cli.backends import render_with

        result = render_with(args.backend, args.cluster, scene, args.spp, args.sampler, device=device, seed=args.seed,
                             progress=not args.quiet, compile=args.compile, intersector=args.intersector)
    else:
        result = render(scene, args.spp, args.sampler, device=device, seed=args.seed, progress=not args.quiet,
                        compile=args.compile or None)
    _check_interrupts()  # nothing written after a Ctrl-C
    check_finite_image(scene_file, result.image)
    metadata = image_metadata(scene_file, scene, args.spp or scene.image.spp, args.sampler or scene.image.sampler,
                              args.seed, args.overrides)
    if args.backend == "mitsuba":  # what rendered it, and the sampler it used
        from renderer.cli.backends import MITSUBA_SAMPLER

        metadata.update(sampler=MITSUBA_SAMPLER, backend="mitsuba",
                        not_mapped=", ".join(result.not_mapped) if result.not_mapped else "nothing")
    write_image(args.output, result.image, args.encoding, metadata=metadata)
    if not args.quiet:
        h, w = result.image.shape[:2]
        print(f"renderer: wrote {args.output} ({w}x{h}, {time.perf_counter() - start:.1f} s)", file=sys.stderr)
    return 0


def _with_camera(scene_file: str, args) -> dict:
    """The scene's dict with its camera replaced by `--camera FILE [--view K]` (a `calibrated` camera, at the
    calibration's image size unless --set gives one)."""
    from renderer.core.params import SceneError
    from camio.checks import read_scene_json

    cfg = read_scene_json(scene_file)
    if not isinstance(cfg, dict):
        raise SceneError(f"{scene_file}: expected an object at the top level, got {cfg!r}")
    cfg.pop("extends", None)
    view = args.view if args.view is not None else 0
    if isinstance(view, str) and view.lstrip("-").isdigit():
        view = int(view)
    cfg["camera"] = {"type": "calibrated", "file": os.path.abspath(args.camera), "view": view}
    if isinstance(cfg.get("image"), dict):
        cfg["image"] = {k: v for k, v in cfg["image"].items() if k not in ("width", "height")}
    return cfg


def cmd_animate(args, device) -> int:
    from renderer.cli.animate import animate, animation_defaults

    path = resolve_scene(args.scene)
    defaults = animation_defaults(path, args.overrides)
    frames = args.frames if args.frames is not None else defaults.get("frames")
    step = args.step if args.step is not None else defaults.get("step")
    for name, value in (("--frames", frames), ("--step", step)):
        if value is None:
            raise UsageError(f"{name}: not given and {path} has no animation.{name[2:]}")
    if os.path.exists(args.output) and not os.path.isdir(args.output):
        raise UsageError(f"{args.output}: not a folder")
    from camio.checks import number

    step = number("--step", step, UsageError, float32=True)
    start = time.perf_counter()
    if args.cluster and device.type != "cpu":
        raise UsageError("--cluster renders on the cluster's CPUs: leave out --device")
    with _removed_on_failure(args.output):
        try:
            animate(path, args.method, frames, step, args.output, args.overrides, device=device,
                    progress=not args.quiet, seed=args.seed, cluster=args.cluster)
        except ImportError as e:
            if not args.cluster:
                raise
            raise UsageError(str(e)) from None
    if not args.quiet:
        print(f"renderer: wrote {frames} frames and frames.csv to {args.output} ({time.perf_counter() - start:.1f} s)",
              file=sys.stderr)
    return 0


@contextlib.contextmanager
def _removed_on_failure(folder: str):
    """On any exception, remove what this run added to `folder` (and the folder, if this run created it)."""
    existed = os.path.isdir(folder)
    before = set(os.listdir(folder)) if existed else set()
    try:
        yield
    except BaseException:
        if os.path.isdir(folder):
            for name in set(os.listdir(folder)) - before:
                target = os.path.join(folder, name)
                shutil.rmtree(target, ignore_errors=True) if os.path.isdir(target) else os.remove(target)
            if not existed and not os.listdir(folder):
                os.rmdir(folder)
        raise


def _check_output(path: str, extensions: tuple[str, ...]) -> None:
    """Fail before any work when the output cannot be written (`camio.files.output_problem`)."""
    problem = output_problem(path, extensions)
    if problem:
        raise UsageError(f"{path}: {problem}")


def check_finite_image(scene_file: str, image) -> None:
    """The tracer computes in float32: a scene whose light intensities, background or material values
    overflow there gives NaN/Inf pixels. They are refused here, never written (docs/file_formats.md)."""
    import torch

    bad = int((~torch.isfinite(image)).sum())
    if bad:
        raise UsageError(f"{scene_file}: the render overflowed float32 in {bad} values (a light intensity, "
                         "background or material value too large); nothing written")


def image_metadata(scene_file: str, scene, spp: int, sampler: str, seed: int, overrides=()) -> dict:
    """What a rendered image records about itself: scene file, overrides, camera, size, spp, sampler, seed."""
    cam = scene.camera
    pose = cam.transform
    position = [round(float(v), 6) for v in pose.position.tolist()] if hasattr(pose, "position") else None
    meta = {"scene": scene_file, "camera": type(cam).__name__}
    if position is not None:
        meta["camera_position"] = position
    meta.update({"size": f"{scene.image.width}x{scene.image.height}", "spp": spp, "sampler": sampler,
                 "seed": seed, "max_depth": scene.image.max_depth})
    if overrides:
        meta["set"] = " ".join(overrides)
    return meta


# ----------------------------------------------------------------------------------------------- gallery


def read_manifest(path: str) -> list[dict]:
    """The gallery manifest: a JSON list of {scene, label, set?: [key.path=value, ...], note?}.

    `scene` is relative to the manifest; `note` is free text for the reader (why the overrides do what they do).
    """
    entries = read_json(path, SceneError, "manifest")
    if not isinstance(entries, list):
        raise SceneError(f"{path}: expected a list of {{scene, label, set}} entries")
    out = []
    for i, e in enumerate(entries):
        where = f"{path}: [{i}]"
        if not isinstance(e, dict):
            raise SceneError(f"{where}: expected an object, got {e!r}")
        for key in e:
            if key not in ("scene", "label", "set", "note"):
                raise SceneError(f"{where}.{key}: unknown key (expected scene, label, set, note)")
        for key in ("scene", "label"):
            if not isinstance(e.get(key), str):
                raise SceneError(f"{where}.{key}: expected a string, got {e.get(key)!r}")
        sets = e.get("set", [])
        if not isinstance(sets, list) or not all(isinstance(s, str) for s in sets):
            raise SceneError(f"{where}.set: expected a list of key.path=value strings, got {sets!r}")
        out.append({"scene": os.path.join(os.path.dirname(path), e["scene"]), "label": e["label"], "set": sets})
    return out


def _panel_overrides(scene, size: int | None, spp: int | None) -> list[str]:
    """Overrides that shrink a scene's image to `size` on its longest side (same view) and set spp."""
    extra = []
    w, h = scene.image.width, scene.image.height
    if size is not None and max(w, h) > size:
        k = size / max(w, h)
        extra += [f"image.width={max(1, round(w * k))}", f"image.height={max(1, round(h * k))}"]
    if spp is not None:
        extra.append(f"image.spp={spp}")
    return extra


def cmd_gallery(args, device) -> int:
    import numpy as np

    from renderer.tracing.render import render
    from renderer.scene.file import load_scene

    entries = read_manifest(args.manifest)
    if not entries:
        raise SceneError(f"{args.manifest}: no entries")
    size = args.size or (128 if args.quick else None)
    panels = []
    start = time.perf_counter()
    for k, entry in enumerate(entries, 1):
        t0 = time.perf_counter()
        scene = load_scene(entry["scene"], entry["set"])
        spp = args.spp or (min(scene.image.spp, 4) if args.quick else None)
        extra = _panel_overrides(scene, size, spp)
        if extra:
            scene = load_scene(entry["scene"], entry["set"] + extra)
        result = render(scene, device=device, seed=args.seed, progress=False)
        check_finite_image(entry["scene"], result.image)
        srgb = linear_to_srgb(result.image.cpu().numpy())
        panels.append((entry["label"], (np.clip(srgb, 0, 1) * 255 + 0.5).astype(np.uint8)))
        print(f"gallery: [{k}/{len(entries)}] {entry['label']} ({scene.image.width}x{scene.image.height}, "
              f"{scene.image.spp} spp) {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    write_contact_sheet(args.output, panels, args.columns)
    print(f"gallery: wrote {args.output} ({len(panels)} panels, {time.perf_counter() - start:.1f} s)",
          file=sys.stderr)
    return 0


def write_contact_sheet(path: str, panels: list, columns: int = 4) -> None:
    """Lay out (label, (H, W, 3) uint8 sRGB image) panels in a labelled grid and write a PNG atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cols = min(columns, len(panels))
    rows = math.ceil(len(panels) / cols)
    panel_in = max(2.0, max(max(img.shape[:2]) for _, img in panels) / 100.0)
    chars_per_line = max(16, int(panel_in * 13))  # about 13 characters of 9-point text per inch
    titles = [textwrap.fill(label, chars_per_line) for label, _ in panels]
    title_in = 0.2 + 0.16 * max(t.count("\n") + 1 for t in titles)
    fig = Figure(figsize=(cols * panel_in, rows * (panel_in + title_in)), dpi=100)
    FigureCanvasAgg(fig)
    for i, ((_, img), title) in enumerate(zip(panels, titles)):
        ax = fig.add_subplot(rows, cols, i + 1)
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": "renderer gallery"})


if __name__ == "__main__":
    sys.exit(main())
