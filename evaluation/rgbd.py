"""RGB-D sequences as benchmark scenes: ``dvpmvs import dataset=7scenes|tum|scannet|rgbd``.

A sequence of colour frames with a depth sensor's depth and a tracker's (or a survey's) poses
becomes a clip of keyframes written as a COLMAP dense workspace with its ground truth:

- ``images/``: the keyframes' colour images (copied; re-encoded as PNG where the importer
  undistorts or resizes them);
- ``sparse/``: one PINHOLE camera per image with the given pose, and sparse points COLMAP
  triangulates from SIFT matches with those poses held fixed (as for Strecha);
- ``stereo/patch-match.cfg``, ``fusion.cfg``;
- ``ground_truth/depth_maps/<image>.bin``: the sensor's depth in metres (COLMAP's map format, the
  colour image's size; 0 where the sensor gave none), for ``dvpmvs eval metric=depth``;
- ``ground_truth/scan_alignment.mlp`` and ``scans/``: ETH3D-format ground truth, one scan per
  keyframe holding its sensor points that another keyframe's sensor confirms
  (:mod:`dvpmvs.evaluation.depth_scans`), and ``eth3d_parameters.json``, for ``dvpmvs eval`` and
  the official ETH3D program;
- ``rgbd.json``: the layout, the source, the keyframes (their frames in the sequence, baselines
  and overlaps) and the rule's parameters.

Layouts (each reader's defaults: depth scale, pixel centres, intrinsics):

- ``7scenes``: a sequence folder of ``frame-XXXXXX.color.{png,jpg}``, ``.depth.png`` (millimetres;
  0 and 65535 mean no depth) and ``.pose.txt`` (4x4 camera-to-world, metres);
  ``camera-intrinsics.txt`` (3x3) where present, else the published 585 / 585 / 320 / 240.
- ``tum``: TUM RGB-D (``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` with ``timestamp tx ty tz
  qx qy qz qw``); colour, depth and pose associated by nearest timestamp within 20 ms (the
  benchmark's ``associate.py``); depth in 1/5000 m; the Freiburg 1, 2 or 3 camera's published
  intrinsics and distortion by the folder's name (``rgbd_dataset_freiburg1_...``), undistorted
  here (the depth is registered to the colour image, so it is undistorted with it).
- ``scannet``: ScanNet's exported frames (``color/N.jpg``, ``depth/N.png`` in millimetres,
  ``pose/N.txt`` camera-to-world, ``intrinsic/intrinsic_depth.txt``); the colour images are
  resized to the depth's size and take the depth camera's intrinsics (ScanNet registers them);
  frames whose pose is not finite (lost tracking) are left out.
- ``rgbd``: ``images/``, ``depth/<image stem>.png`` (16-bit, the same size), ``K.txt`` (3x3, or
  ``fx fy cx cy``) and ``poses.txt`` (a line per image: its name and 16 numbers, the 4x4
  camera-to-world matrix row by row, or 12 for its top 3x4); millimetres unless ``depth_scale``.

Every layout's intrinsics put pixel centres at integers (OpenCV's and these datasets'
convention, and the dense stage's: pixel (row, col) is the image point (col, row));
``pixel_centre=half`` reads intrinsics whose top-left pixel centre is (0.5, 0.5).

Keyframes (a documented rule, :func:`select_keyframes`): the clip starts at frame ``start``; each
next keyframe is the first later frame at least ``min_baseline`` metres from the last keyframe,
provided at least ``min_overlap`` of the last keyframe's sensor points (a grid of them) are seen
by that frame at the depth its sensor measures there (within 5 %); where the overlap falls
below ``min_overlap`` before the baseline is reached, the last frame that still overlapped is
taken. A clip has ``views`` keyframes.
"""

from __future__ import annotations

import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path, write_depth_map
from dvpmvs.validation import check_field_types

__all__ = [
    "LAYOUTS",
    "RGBDFrame",
    "RGBDOptions",
    "RGBDSequence",
    "import_rgbd",
    "read_sequence",
    "select_keyframes",
]

LAYOUTS = ("7scenes", "tum", "scannet", "rgbd")

# Published intrinsics (fx, fy, cx, cy) and distortion (k1, k2, p1, p2, k3).
SEVEN_SCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
TUM_CAMERAS = {
    "freiburg1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
_DEPTH_SCALE = {"7scenes": 1000.0, "tum": 5000.0, "scannet": 1000.0, "rgbd": 1000.0}
_TUM_MAX_DIFFERENCE = 0.02  # seconds between associated colour, depth and pose
_OVERLAP_TOLERANCE = 0.05  # a grid point is seen by a frame whose sensor agrees within 5 %
_OVERLAP_STEP = 8  # the grid of sensor points the overlap is measured on (pixels)


@dataclass(frozen=True)
class RGBDOptions:
    """How a sequence becomes a clip (``rgbd.*`` of ``dvpmvs import``); ``None``: the layout's."""

    views: int = 10
    start: int = 0
    min_baseline: float = 0.05
    min_overlap: float = 0.6
    depth_scale: float | None = None
    pixel_centre: str | None = None
    intrinsics: list[float] | None = None
    confirm_tolerance: float = 0.02
    calibrate_color: bool | None = None

    def __post_init__(self):
        check_field_types(self, "rgbd.")
        if self.views < 2:
            raise DvpmvsError(f"rgbd.views={self.views}: a clip needs at least 2 views")
        if self.start < 0:
            raise DvpmvsError(f"rgbd.start={self.start}: give a frame index from 0")
        if not self.min_baseline >= 0:
            raise DvpmvsError(f"rgbd.min_baseline={self.min_baseline}: give metres, 0 or more")
        if not 0 < self.min_overlap <= 1:
            raise DvpmvsError(f"rgbd.min_overlap={self.min_overlap}: give a share in (0, 1]")
        if self.depth_scale is not None and not self.depth_scale > 0:
            raise DvpmvsError(
                f"rgbd.depth_scale={self.depth_scale}: give the sensor's units per metre "
                f"(1000 for millimetres, 5000 for TUM)"
            )
        if self.pixel_centre not in (None, "integer", "half"):
            raise DvpmvsError(
                f"rgbd.pixel_centre={self.pixel_centre}: choose integer (OpenCV's convention: "
                f"the top-left pixel's centre is (0, 0)) or half (it is (0.5, 0.5))"
            )
        if self.intrinsics is not None and (
            len(self.intrinsics) != 4 or not all(v > 0 for v in self.intrinsics)
        ):
            raise DvpmvsError(f"rgbd.intrinsics={self.intrinsics}: give [fx, fy, cx, cy] in pixels")
        if not 0 < self.confirm_tolerance < 1:
            raise DvpmvsError(
                f"rgbd.confirm_tolerance={self.confirm_tolerance}: give a relative depth "
                f"difference in (0, 1), e.g. 0.02"
            )


@dataclass(frozen=True)
class RGBDFrame:
    """One frame: its colour and depth files and its camera-to-world pose (4x4, metres)."""

    index: int
    color: Path
    depth: Path
    camera_to_world: np.ndarray = field(repr=False)
    name: str = ""  # the image's name in the workspace

    @property
    def center(self) -> np.ndarray:
        return self.camera_to_world[:3, 3]


@dataclass
class RGBDSequence:
    """A sequence's frames in order with its camera: ``K`` (pixel centres at integers) for
    images of ``size`` (width, height), lens ``distortion`` (OpenCV's k1 k2 p1 p2 k3) or None,
    and the depth's units per metre."""

    layout: str
    frames: list[RGBDFrame]
    K: np.ndarray
    size: tuple[int, int]
    depth_scale: float
    distortion: np.ndarray | None = None
    resize: bool = False  # the colour images are resized to ``size`` (ScanNet)
    # The colour images' own camera is unknown (7-Scenes publishes the depth camera's alone):
    # calibrate it against the poses (:func:`calibrate_color_camera`).
    calibrate_color: bool = False

    def read_depth(self, frame: RGBDFrame) -> np.ndarray:
        """The frame's depth in metres (float32, ``size``), 0 where the sensor gave none;
        undistorted with the colour image where the camera has distortion."""
        raw = cv2.imread(str(frame.depth), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.ndim != 2 or raw.dtype != np.uint16:
            raise DvpmvsError(
                f"{frame.depth} is not a 16-bit single-channel depth image; the sensor's depth "
                f"is read as 16-bit PNG"
            )
        if (raw.shape[1], raw.shape[0]) != self.size:
            raise DvpmvsError(
                f"{frame.depth} is {raw.shape[1]}x{raw.shape[0]}, its colour image "
                f"{self.size[0]}x{self.size[1]}; give depth registered to the colour images"
            )
        depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        depth[(raw == 0) | (raw == 65535)] = 0
        if self.distortion is not None:
            depth = cv2.remap(depth, *self._undistort_maps(), cv2.INTER_NEAREST)
        return depth

    def read_color(self, frame: RGBDFrame) -> np.ndarray:
        """The frame's colour image (BGR) as the workspace holds it: undistorted, resized."""
        image = cv2.imread(str(frame.color), cv2.IMREAD_COLOR)
        if image is None:
            raise DvpmvsError(f"cannot read the colour image {frame.color}")
        if self.resize:
            image = cv2.resize(image, self.size, interpolation=cv2.INTER_AREA)
        elif (image.shape[1], image.shape[0]) != self.size:
            raise DvpmvsError(
                f"{frame.color} is {image.shape[1]}x{image.shape[0]}, the sequence's camera "
                f"{self.size[0]}x{self.size[1]}"
            )
        if self.distortion is not None:
            image = cv2.remap(image, *self._undistort_maps(), cv2.INTER_LINEAR)
        return image

    def _undistort_maps(self):
        if not hasattr(self, "_maps"):
            self._maps = cv2.initUndistortRectifyMap(
                self.K, self.distortion, None, self.K, self.size, cv2.CV_32FC1
            )
        return self._maps


# -- readers ---------------------------------------------------------------------------------


def _read_matrix(path: Path, shape: tuple[int, int], what: str) -> np.ndarray:
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise DvpmvsError(f"cannot read {what} {path}: {exc}") from None
    if values.size != shape[0] * shape[1]:
        raise DvpmvsError(
            f"{path}: {what} has {shape[0] * shape[1]} numbers ({shape[0]}x{shape[1]}); "
            f"found {values.size}"
        )
    return values.reshape(shape)


def _intrinsics(fx, fy, cx, cy) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _image_size(path: Path) -> tuple[int, int]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DvpmvsError(f"cannot read the image {path}")
    return image.shape[1], image.shape[0]


def _read_7scenes(folder: Path) -> RGBDSequence:
    colors = sorted(p for p in folder.glob("frame-*.color.*") if p.suffix in (".png", ".jpg"))
    if not colors:
        raise DvpmvsError(
            f"{folder} holds no frame-XXXXXX.color.png/.jpg: not a 7-Scenes sequence folder "
            f"(give source= a seq-NN folder)"
        )
    frames = []
    for i, color in enumerate(colors):
        stem = color.name.split(".color.")[0]
        depth, pose = folder / f"{stem}.depth.png", folder / f"{stem}.pose.txt"
        for path, what in ((depth, "depth image"), (pose, "pose")):
            if not path.is_file():
                raise DvpmvsError(f"{color.name} has no {what} {path.name} in {folder}")
        frames.append(
            RGBDFrame(i, color, depth, _read_matrix(pose, (4, 4), "the pose"), color.name)
        )
    intrinsics = folder / "camera-intrinsics.txt"
    K = (
        _read_matrix(intrinsics, (3, 3), "the intrinsics")
        if intrinsics.is_file()
        else _intrinsics(*SEVEN_SCENES_INTRINSICS)
    )
    return RGBDSequence(
        "7scenes",
        frames,
        K,
        _image_size(colors[0]),
        _DEPTH_SCALE["7scenes"],
        calibrate_color=True,
    )


def _tum_list(path: Path) -> list[tuple[float, list[str]]]:
    if not path.is_file():
        raise DvpmvsError(f"{path.parent} is not a TUM RGB-D sequence: {path.name} is missing")
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        words = line.replace(",", " ").split()
        if not words or words[0].startswith("#"):
            continue
        try:
            rows.append((float(words[0]), words[1:]))
        except ValueError:
            raise DvpmvsError(
                f"{path}, line {number}: {line!r} does not start with a time"
            ) from None
    return rows


def _nearest(times: np.ndarray, t: float) -> int | None:
    """The index of the time in sorted ``times`` nearest ``t``, if within the benchmark's 20 ms."""
    if times.size == 0:
        return None
    i = int(np.searchsorted(times, t))
    best = min((j for j in (i - 1, i) if 0 <= j < times.size), key=lambda j: abs(times[j] - t))
    return best if abs(times[best] - t) <= _TUM_MAX_DIFFERENCE else None


def _quaternion_pose(values: list[str]) -> np.ndarray:
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in values[:7])
    q = np.array([qw, qx, qy, qz])
    w, x, y, z = q / np.linalg.norm(q)
    pose = np.eye(4)
    pose[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    pose[:3, 3] = [tx, ty, tz]
    return pose


def _read_tum(folder: Path, intrinsics) -> RGBDSequence:
    rgb = _tum_list(folder / "rgb.txt")
    depth = _tum_list(folder / "depth.txt")
    truth = [(t, v) for t, v in _tum_list(folder / "groundtruth.txt") if len(v) >= 7]
    depth_times = np.array([t for t, _ in depth])
    truth_times = np.array([t for t, _ in truth])
    frames = []
    for t, (name, *_) in rgb:
        d, g = _nearest(depth_times, t), _nearest(truth_times, t)
        if d is None or g is None:
            continue
        color = folder / name
        frames.append(
            RGBDFrame(
                len(frames),
                color,
                folder / depth[d][1][0],
                _quaternion_pose(truth[g][1]),
                color.name,
            )
        )
    if not frames:
        raise DvpmvsError(
            f"{folder}: no colour image has a depth image and a pose within 20 ms of its time"
        )
    distortion = None
    if intrinsics is None:
        camera = next((c for c in TUM_CAMERAS if c in folder.resolve().name), None)
        if camera is None:
            raise DvpmvsError(
                f"{folder}: the folder's name names no Freiburg camera (freiburg1, 2 or 3), whose "
                f"published intrinsics the import would use; give rgbd.intrinsics=[fx,fy,cx,cy]"
            )
        intrinsics, coefficients = TUM_CAMERAS[camera]
        if any(coefficients):
            distortion = np.array(coefficients)
    return RGBDSequence(
        "tum",
        frames,
        _intrinsics(*intrinsics),
        _image_size(frames[0].color),
        _DEPTH_SCALE["tum"],
        distortion,
    )


def _read_scannet(folder: Path) -> RGBDSequence:
    color_dir = folder / "color"
    if not color_dir.is_dir() or not (folder / "intrinsic" / "intrinsic_depth.txt").is_file():
        raise DvpmvsError(
            f"{folder} is not a ScanNet export: color/ and intrinsic/intrinsic_depth.txt are "
            f"needed (ScanNet's SensReader writes them)"
        )
    numbered = sorted(
        (int(p.stem), p) for p in color_dir.iterdir() if p.stem.isdigit() and p.suffix == ".jpg"
    )
    frames = []
    for number, color in numbered:
        depth, pose = folder / "depth" / f"{number}.png", folder / "pose" / f"{number}.txt"
        if not depth.is_file() or not pose.is_file():
            raise DvpmvsError(f"{color} has no {depth} or {pose}")
        matrix = _read_matrix(pose, (4, 4), "the pose")
        if not np.isfinite(matrix).all():
            continue  # ScanNet marks frames its tracking lost with -inf
        frames.append(RGBDFrame(len(frames), color, depth, matrix, f"{number:06d}.png"))
    if not frames:
        raise DvpmvsError(f"{folder}: no frame with a finite pose")
    K = _read_matrix(folder / "intrinsic" / "intrinsic_depth.txt", (4, 4), "the intrinsics")[:3, :3]
    return RGBDSequence(
        "scannet", frames, K, _image_size(frames[0].depth), _DEPTH_SCALE["scannet"], resize=True
    )


def _read_plain(folder: Path) -> RGBDSequence:
    for needed in ("images", "depth", "K.txt", "poses.txt"):
        if not (folder / needed).exists():
            raise DvpmvsError(
                f"{folder} is not an rgbd layout: {needed} is missing (images/, depth/, K.txt, "
                f"poses.txt)"
            )
    values = np.array((folder / "K.txt").read_text().split(), dtype=np.float64)
    if values.size == 4:
        K = _intrinsics(*values)
    elif values.size == 9:
        K = values.reshape(3, 3)
    else:
        raise DvpmvsError(f"{folder / 'K.txt'}: give a 3x3 matrix or fx fy cx cy")
    frames = []
    for number, line in enumerate((folder / "poses.txt").read_text().splitlines(), 1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if len(words) not in (13, 17):
            raise DvpmvsError(
                f"{folder / 'poses.txt'}, line {number}: an image name and 16 numbers (the 4x4 "
                f"camera-to-world matrix row by row) or 12 (its top 3x4); found {len(words) - 1}"
            )
        pose = np.eye(4)
        pose[: (len(words) - 1) // 4] = np.array(words[1:], dtype=np.float64).reshape(-1, 4)
        color = folder / "images" / words[0]
        depth = folder / "depth" / f"{Path(words[0]).stem}.png"
        for path in (color, depth):
            if not path.is_file():
                raise DvpmvsError(f"{folder / 'poses.txt'}, line {number}: {path} is missing")
        frames.append(RGBDFrame(len(frames), color, depth, pose, Path(words[0]).name))
    if not frames:
        raise DvpmvsError(f"{folder / 'poses.txt'} names no image")
    return RGBDSequence("rgbd", frames, K, _image_size(frames[0].color), _DEPTH_SCALE["rgbd"])


def read_sequence(layout: str, folder: str | Path, options: RGBDOptions) -> RGBDSequence:
    """The frames and camera of the sequence in ``folder`` (``layout``: one of :data:`LAYOUTS`),
    with ``options``' depth scale, pixel centres and intrinsics where given."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DvpmvsError(f"the sequence folder {folder} does not exist")
    if layout == "7scenes":
        sequence = _read_7scenes(folder)
    elif layout == "tum":
        sequence = _read_tum(folder, options.intrinsics)
    elif layout == "scannet":
        sequence = _read_scannet(folder)
    elif layout == "rgbd":
        sequence = _read_plain(folder)
    else:
        raise DvpmvsError(f"unknown RGB-D layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    if options.intrinsics is not None and layout != "tum":
        sequence.K = _intrinsics(*options.intrinsics)
    if options.pixel_centre == "half":
        sequence.K = sequence.K.copy()
        sequence.K[:2, 2] -= 0.5
    if options.depth_scale is not None:
        sequence.depth_scale = float(options.depth_scale)
    if options.calibrate_color is not None:
        sequence.calibrate_color = options.calibrate_color
    # Names repeat only across a TUM sequence's folders or a user's subfolders: number them then.
    if len({f.name for f in sequence.frames}) < len(sequence.frames):
        sequence.frames = [
            RGBDFrame(
                f.index, f.color, f.depth, f.camera_to_world, f"{f.index:06d}{f.color.suffix}"
            )
            for f in sequence.frames
        ]
    if sequence.distortion is not None or sequence.resize:
        sequence.frames = [
            RGBDFrame(f.index, f.color, f.depth, f.camera_to_world, f"{Path(f.name).stem}.png")
            for f in sequence.frames
        ]
    return sequence


# -- keyframes ---------------------------------------------------------------------------------


def _overlap(sequence: RGBDSequence, a: RGBDFrame, depth_a, b: RGBDFrame, depth_b) -> float:
    """The share of ``a``'s sensor points (a grid) that ``b`` sees at the depth its sensor
    measures there (within 5 %)."""
    from dvpmvs.evaluation.depth_scans import backproject, visible_in

    grid = np.zeros_like(depth_a, bool)
    grid[::_OVERLAP_STEP, ::_OVERLAP_STEP] = True
    rows, cols = np.nonzero(grid & (depth_a > 0))
    if rows.size == 0:
        return 0.0
    R_a, t_a = _world_to_camera(a)
    world = backproject(depth_a, sequence.K, R_a, t_a, rows, cols)
    R_b, t_b = _world_to_camera(b)
    return float(visible_in(world, R_b, t_b, sequence.K, depth_b, _OVERLAP_TOLERANCE).mean())


def _world_to_camera(frame: RGBDFrame) -> tuple[np.ndarray, np.ndarray]:
    R_cw = frame.camera_to_world[:3, :3]
    R = R_cw.T
    return R, -R @ frame.center


def select_keyframes(sequence: RGBDSequence, options: RGBDOptions) -> list[dict]:
    """The clip's keyframes by the module's rule: per keyframe its frame, the baseline to the
    keyframe before it (metres) and their overlap."""
    frames = sequence.frames
    if options.start >= len(frames):
        raise DvpmvsError(
            f"rgbd.start={options.start}: the sequence has {len(frames)} frames (0-{len(frames) - 1})"
        )
    depths: dict[int, np.ndarray] = {}

    def depth(i: int) -> np.ndarray:
        if i not in depths:
            depths[i] = sequence.read_depth(frames[i])
        return depths[i]

    chosen = [{"frame": options.start, "baseline": 0.0, "overlap": 1.0}]
    while len(chosen) < options.views:
        last = chosen[-1]["frame"]
        pick = None
        for j in range(last + 1, len(frames)):
            overlap = _overlap(sequence, frames[last], depth(last), frames[j], depth(j))
            if overlap < options.min_overlap:
                break
            baseline = float(np.linalg.norm(frames[j].center - frames[last].center))
            pick = {"frame": j, "baseline": baseline, "overlap": overlap}
            if baseline >= options.min_baseline:
                break
        if pick is None:
            raise DvpmvsError(
                f"frame {frames[last].color.name} (keyframe {len(chosen)} of the clip) has no later "
                f"frame that sees {options.min_overlap:.0%} of it, or the sequence ends there: "
                f"{len(chosen)} of rgbd.views={options.views} keyframes found from "
                f"rgbd.start={options.start}; give an earlier start, fewer views or a lower "
                f"rgbd.min_overlap"
            )
        for i in list(depths):
            if i < pick["frame"]:
                del depths[i]  # only the last keyframe's and later frames' depth are read again
        chosen.append(pick)
    return chosen


# -- the workspace ---------------------------------------------------------------------------


def calibrate_color_camera(sparse: Path) -> tuple[np.ndarray, dict]:
    """The colour images' intrinsics (one pinhole camera, square pixels) that fit the
    triangulated model in ``sparse`` best with its poses held fixed: COLMAP's bundle adjustment
    refining the focal length and principal point and the points alone. Returns K and the
    mean reprojection error before and after."""
    import pycolmap

    source = pycolmap.Reconstruction(str(sparse))
    first = source.cameras[min(source.cameras)]
    K = first.calibration_matrix() + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(
        pycolmap.Camera(
            model="SIMPLE_PINHOLE",
            width=first.width,
            height=first.height,
            params=[(K[0, 0] + K[1, 1]) / 2, K[0, 2], K[1, 2]],
            camera_id=1,
        )
    )
    for image in source.images.values():
        copy = pycolmap.Image(name=image.name, camera_id=1, image_id=image.image_id)
        copy.points2D = pycolmap.Point2DList([pycolmap.Point2D(p.xy) for p in image.points2D])
        model.add_image_with_trivial_frame(copy, image.cam_from_world())
    for point in source.points3D.values():
        track = pycolmap.Track()
        for element in point.track.elements:
            track.add_element(element.image_id, element.point2D_idx)
        model.add_point3D(point.xyz, track, point.color)
    model.update_point_3d_errors()
    before = model.compute_mean_reprojection_error()
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = True
    options.refine_principal_point = True
    options.refine_extra_params = False
    options.refine_rig_from_world = False  # the tracked poses are the reference
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in model.images:
        config.add_image(image_id)
    pycolmap.create_default_bundle_adjuster(options, config, model).solve()
    model.update_point_3d_errors()
    f, cx, cy = model.cameras[1].params
    # COLMAP's keypoints put the top-left pixel's centre at (0.5, 0.5); the workspace's
    # intrinsics are the dense stage's (pixel centres at integers).
    return _intrinsics(f, f, cx - 0.5, cy - 0.5), {
        "reprojection_error_px_before": before,
        "reprojection_error_px": model.compute_mean_reprojection_error(),
    }


def _registered_depth(depth: np.ndarray, K_depth: np.ndarray, K_color: np.ndarray) -> np.ndarray:
    """The depth camera's map seen through the colour camera's intrinsics at the same pose: each
    pixel moved to where the colour camera sees its point, the nearest depth kept."""
    rows, cols = np.nonzero(depth > 0)
    z = depth[rows, cols]
    u = K_color[0, 0] * (cols - K_depth[0, 2]) / K_depth[0, 0] + K_color[0, 2]
    v = K_color[1, 1] * (rows - K_depth[1, 2]) / K_depth[1, 1] + K_color[1, 2]
    col, row = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
    h, w = depth.shape
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    registered = np.full(depth.shape, np.inf, np.float32)
    np.minimum.at(registered, (row[inside], col[inside]), z[inside])
    registered[np.isinf(registered)] = 0
    return registered


_CALIBRATION_ROUNDS = 6  # bundle adjustment, then triangulation with its intrinsics, again
_CALIBRATION_CONVERGED = 0.5  # px: the focal length moved less in the last round


def import_rgbd(
    layout: str,
    source: str | Path,
    out: str | Path,
    options: RGBDOptions = RGBDOptions(),
    max_image_size: int = 1600,
    num_threads: int = -1,
    num_sources: int = 10,
    progress=None,
) -> dict:
    """Write the clip of the sequence in ``source`` into ``out`` (see the module's doc); returns
    its statistics (also in ``out/rgbd.json``)."""
    from dvpmvs.evaluation.depth_scans import beam_parameters, write_scans
    from dvpmvs.evaluation.report import write_json
    from dvpmvs.evaluation.strecha import StrechaCamera, import_with_known_poses

    sequence = read_sequence(layout, source, options)
    if progress:
        progress(f"keyframes of {len(sequence.frames)} frames")
    keys = select_keyframes(sequence, options)
    frames = [sequence.frames[k["frame"]] for k in keys]
    out = Path(out)
    images = out / "images"
    if images.is_dir():
        shutil.rmtree(images)  # the images of another clip would join this one's model
    images.mkdir(parents=True)
    ground_truth = out / "ground_truth"
    if ground_truth.is_dir():
        shutil.rmtree(ground_truth)
    width, height = sequence.size
    cameras, depths, cams = {}, [], []
    for frame in frames:
        if progress:
            progress(f"image and sensor depth {frame.name}")
        target = images / frame.name
        if sequence.distortion is None and not sequence.resize:
            with atomic_path(target, suffix=frame.color.suffix) as tmp:
                shutil.copyfile(frame.color, tmp)
            sequence.read_color(frame)  # the size checked
        else:
            with atomic_path(target, suffix=".png") as tmp:
                if not cv2.imwrite(str(tmp), sequence.read_color(frame)):
                    raise DvpmvsError(f"could not write {target}")
        depths.append(sequence.read_depth(frame))
        R, t = _world_to_camera(frame)
        cams.append((R, t))
        cameras[frame.name] = StrechaCamera(
            sequence.K, frame.camera_to_world[:3, :3], frame.center, width, height
        )
    stats = import_with_known_poses(
        images, cameras, out, max_image_size, num_threads, num_sources, progress
    )
    K_color, calibration = sequence.K, None
    if sequence.calibrate_color:
        calibration = {"focal_given": float(sequence.K[0, 0]), "rounds": 0}
        for _ in range(_CALIBRATION_ROUNDS):
            if progress:
                progress("calibrating the colour camera against the poses")
            previous = K_color
            K_color, errors = calibrate_color_camera(out / "sparse")
            calibration.setdefault(
                "reprojection_error_px_before", errors["reprojection_error_px_before"]
            )
            calibration["rounds"] += 1
            calibration.setdefault("focal_per_round", []).append(round(float(K_color[0, 0]), 2))
            for name, camera in cameras.items():
                cameras[name] = StrechaCamera(K_color, camera.R.T, camera.center, width, height)
            stats = import_with_known_poses(
                images, cameras, out, max_image_size, num_threads, num_sources, progress
            )
            if abs(K_color[0, 0] - previous[0, 0]) < _CALIBRATION_CONVERGED:
                break
        calibration.update(
            focal=float(K_color[0, 0]),
            principal_point=[float(K_color[0, 2]), float(K_color[1, 2])],
            reprojection_error_px=stats["mean_reprojection_error_px"],
        )
    for frame, depth in zip(frames, depths):  # on the colour camera's pixels
        if calibration is not None:
            depth = _registered_depth(depth, sequence.K, K_color)
        write_depth_map(ground_truth / "depth_maps" / f"{frame.name}.bin", depth)
    if progress:
        progress("ground-truth scans")
    stems = [Path(f.name).stem for f in frames]
    if len(set(stems)) < len(stems):
        stems = [f"{i:04d}" for i in range(len(frames))]
    scan_points = write_scans(
        ground_truth, stems, depths, cams, sequence.K, options.confirm_tolerance
    )
    write_json(ground_truth / "eth3d_parameters.json", beam_parameters(float(sequence.K[0, 0])))
    valid = [float((d > 0).mean()) for d in depths]
    record = {
        "layout": layout,
        "source": str(Path(source).resolve()),
        "options": asdict(options),
        "camera": {
            "K": K_color.tolist(),
            "depth_K": sequence.K.tolist(),
            "color_calibration": calibration,
            "size": list(sequence.size),
            "depth_scale": sequence.depth_scale,
            "undistorted": sequence.distortion is not None,
        },
        "keyframes": [
            {
                "image": frame.name,
                "frame": key["frame"],
                "color": str(frame.color.relative_to(Path(source))),
                "baseline": round(key["baseline"], 4),
                "overlap": round(key["overlap"], 4),
                "sensor_depth_share": round(share, 4),
            }
            for frame, key, share in zip(frames, keys, valid)
        ],
        "frames_in_sequence": len(sequence.frames),
        "scan_points": scan_points,
        "sparse": stats,
    }
    write_json(out / "rgbd.json", record)
    return {
        "keyframes": len(frames),
        "frames": f"{keys[0]['frame']}-{keys[-1]['frame']} of {len(sequence.frames)}",
        "mean_baseline_m": float(np.mean([k["baseline"] for k in keys[1:]])),
        "sensor_depth_share": float(np.mean(valid)),
        "scan_points": scan_points,
        **{k: v for k, v in stats.items() if k in ("points3D", "mean_reprojection_error_px")},
    }
