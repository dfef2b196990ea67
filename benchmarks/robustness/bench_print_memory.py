"""Peak memory of `tiltfit target print` per pixel of the PNG, against OpenCV's ChArUco board image (issue 33 §4:
a 44 × 44 ChArUco board at 300 dpi once peaked at 10 GB, about 141 bytes a pixel).

Each case runs in a fresh process: the libraries are imported and a small print (10 dpi) is written first (so
what the first call loads is in the baseline, but not a strip's working set), then the page; peak memory is the process's maximum resident set
(`resource.getrusage`), and the figure is (peak after − peak before) / pixels. The peer is OpenCV's
`CharucoBoard.generateImage` of the same board at the same pixel size, then `cv2.imwrite` of the PNG, measured
the same way. Medians over --repeats processes per case.

    python benchmarks/robustness/bench_print_memory.py           # -> benchmarks/results/print_memory.{json,md}
"""
from __future__ import annotations

import datetime
import json
import os
import statistics
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks.results_io import ROOT, run_benchmark, write_lines  # noqa: E402

# (name, columns = rows of squares, square mm, dpi): up to the 0.71 m board at 300 dpi (72 megapixels)
CASES = [("charuco 11x11, 16 mm", 11, 16.0, 300.0), ("charuco 22x22, 16 mm", 22, 16.0, 300.0),
         ("charuco 44x44, 16 mm", 44, 16.0, 150.0), ("charuco 44x44, 16 mm", 44, 16.0, 300.0)]
DICTIONARY = "DICT_5X5_1000"
MARKER_RATIO = 0.75

OURS = """
import json, resource, sys, tempfile, os
from tiltfit.target.layout import charuco_from_dict
from tiltfit.target.printable import write_printable
n, square, dpi = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
board = lambda k: charuco_from_dict({{"type": "charuco", "dictionary": "{dictionary}", "squares": [k, k],
                                     "square_mm": square, "marker_mm": square * {ratio}}})
t = board(n)
d = tempfile.mkdtemp()
write_printable(board(3), os.path.join(d, "w.png"), None, dpi=10)  # loads the code, allocates little
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
write_printable(t, os.path.join(d, "p.png"), None, dpi=dpi)
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
import OpenImageIO as oiio
spec = oiio.ImageInput.open(os.path.join(d, "p.png")).spec()
print(json.dumps({{"kib_before": before, "kib_after": after, "width": spec.width, "height": spec.height}}))
"""

PEER = """
import json, resource, sys, tempfile, os
import cv2
n, square, dpi, width, height = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
d = tempfile.mkdtemp()
aruco = cv2.aruco
board = aruco.CharucoBoard((n, n), square, square * {ratio}, aruco.getPredefinedDictionary(aruco.{dictionary}))
small = aruco.CharucoBoard((3, 3), square, square * {ratio}, aruco.getPredefinedDictionary(aruco.{dictionary}))
cv2.imwrite(os.path.join(d, "w.png"), small.generateImage((300, 300)))
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
img = board.generateImage((width, height))
cv2.imwrite(os.path.join(d, "p.png"), img)
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({{"kib_before": before, "kib_after": after, "width": width, "height": height}}))
"""


def _run(code: str, *args) -> dict:
    env = {**os.environ, "PYTHONPATH": ROOT, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, env=env,
                         cwd=ROOT)
    if out.returncode:
        raise SystemExit(f"bench_print_memory: a case failed: {out.stderr.strip().splitlines()[-1:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _per_pixel(r: dict) -> float:
    return (r["kib_after"] - r["kib_before"]) * 1024.0 / (r["width"] * r["height"])


def measure(args) -> dict:
    ours_code = OURS.format(ratio=MARKER_RATIO, dictionary=DICTIONARY)
    peer_code = PEER.format(ratio=MARKER_RATIO, dictionary=DICTIONARY)
    rows = []
    for name, n, square, dpi in CASES:
        ours, peer = [], []
        for _ in range(args.repeats):
            ours.append(_run(ours_code, n, square, dpi))
            peer.append(_run(peer_code, n, square, dpi, ours[-1]["width"], ours[-1]["height"]))
        o = statistics.median(_per_pixel(r) for r in ours)
        p = statistics.median(_per_pixel(r) for r in peer)
        rows.append({"case": name, "dpi": dpi, "width_px": ours[0]["width"], "height_px": ours[0]["height"],
                     "megapixels": ours[0]["width"] * ours[0]["height"] / 1e6,
                     "ours_bytes_per_pixel": o, "opencv_bytes_per_pixel": p,
                     "ours_peak_increase_mib": statistics.median((r["kib_after"] - r["kib_before"]) / 1024 for r in ours),
                     "opencv_peak_increase_mib": statistics.median((r["kib_after"] - r["kib_before"]) / 1024
                                                                   for r in peer),
                     "ratio_ours_over_opencv": o / p if p > 0 else None,
                     "ours_runs": ours, "opencv_runs": peer})
        print(f"{name} at {dpi:g} dpi: ours {o:.2f} B/px, OpenCV {p:.2f} B/px", file=sys.stderr, flush=True)
    return {"date": datetime.date.today().isoformat(), "repeats": args.repeats, "dictionary": DICTIONARY,
            "cases": rows}


def write_markdown(path: str, res: dict) -> None:
    lines = [f"# Peak memory of `tiltfit target print --png` per pixel ({res['date']})", "",
             "Peak resident memory above the process's peak before the call (libraries loaded, a 10-dpi print "
             "written), per PNG pixel; median of "
             f"{res['repeats']} fresh processes. Peer: OpenCV's `CharucoBoard.generateImage` + `cv2.imwrite` of "
             f"the same board ({res['dictionary']}) at the same size. Before the strip writer: about 141 B/px "
             "(10.1 GB for the 44 × 44 board at 300 dpi, issue 33).", "",
             "| board | dpi | PNG (px) | MP | ours (B/px) | OpenCV (B/px) | ours / OpenCV | ours (MiB) | OpenCV (MiB) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in res["cases"]:
        ratio = "—" if r["ratio_ours_over_opencv"] is None else f"{r['ratio_ours_over_opencv']:.2f}"
        lines.append(f"| {r['case']} | {r['dpi']:g} | {r['width_px']} × {r['height_px']} | {r['megapixels']:.1f} | "
                     f"{r['ours_bytes_per_pixel']:.2f} | {r['opencv_bytes_per_pixel']:.2f} | {ratio} | "
                     f"{r['ours_peak_increase_mib']:.0f} | {r['opencv_peak_increase_mib']:.0f} |")
    lines.append("")
    lines.append("Reproduce: `python benchmarks/robustness/bench_print_memory.py`.")
    write_lines(path, lines)


if __name__ == "__main__":
    sys.exit(run_benchmark(__doc__, "print_memory", measure, write_markdown, repeats=3))
