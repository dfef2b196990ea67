"""Rebuild this folder's crops and published corners from /work/shared/data/real/charuco_webcam (see README.md)."""
import collections
import csv
import os

import cv2
import numpy as np

SOURCE = "/work/shared/data/real/charuco_webcam"
HERE = os.path.dirname(os.path.abspath(__file__))


def _frames():
    cap = cv2.VideoCapture(os.path.join(SOURCE, "cam_0.mp4"))
    out = []
    while True:
        ok, f = cap.read()
        if not ok:
            return np.stack(out)
        out.append(f)


def main():
    frames = _frames()
    pub = collections.defaultdict(dict)
    for r in csv.DictReader(open(os.path.join(SOURCE, "published_corners_cam0.csv"))):
        pub[int(r["frame_index"])][int(r["keypoint_id"])] = (float(r["img_loc_x"]), float(r["img_loc_y"]))
    rows = []
    for fi in (26, 36, 39):
        xy = np.array(list(pub[fi].values()))
        x0, y0 = int(max(0, xy[:, 0].min() - 160)), int(max(0, xy[:, 1].min() - 160))
        x1, y1 = int(min(1280, xy[:, 0].max() + 160)), int(min(720, xy[:, 1].max() + 160))
        g = cv2.cvtColor(frames[fi], cv2.COLOR_BGR2GRAY)[y0:y1, x0:x1]
        cv2.imwrite(os.path.join(HERE, f"frame_{fi:02d}.png"), g, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        rows += [(f"frame_{fi:02d}.png", k, round(x - x0, 4), round(y - y0, 4)) for k, (x, y) in sorted(pub[fi].items())]
    with open(os.path.join(HERE, "published_corners.csv"), "w") as f:
        f.write("image,corner_id,x_px,y_px\n")
        f.writelines(",".join(map(str, r)) + "\n" for r in rows)


#: Four frames with all 12 corners, spread over the stream: the 4-view case of issue 33 §5.
FOUR_VIEWS = (26, 36, 39, 44)


def four_views():
    """published_corners_4views.csv: the published corners of `FOUR_VIEWS` in the full 1280×720 frame."""
    pub = collections.defaultdict(dict)
    for r in csv.DictReader(open(os.path.join(SOURCE, "published_corners_cam0.csv"))):
        pub[int(r["frame_index"])][int(r["keypoint_id"])] = (float(r["img_loc_x"]), float(r["img_loc_y"]))
    with open(os.path.join(HERE, "published_corners_4views.csv"), "w") as f:
        f.write("frame,corner_id,x_px,y_px\n")
        for fi in FOUR_VIEWS:
            f.writelines(f"{fi},{k},{x:.4f},{y:.4f}\n" for k, (x, y) in sorted(pub[fi].items()))


if __name__ == "__main__":
    main()
    four_views()
