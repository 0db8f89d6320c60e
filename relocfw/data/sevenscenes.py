"""Microsoft 7-Scenes layout: seq-XX/frame-NNNNNN.color.{png,jpg} + .pose.txt.

Each frame also gets its cameras and, where the folder has it, its depth map:
    camera      the colour camera. A Kinect v1 has two sensors: 7-Scenes' one published
                calibration, focal length 585 and principal point (320, 240), which
                `camera-intrinsics.txt` holds in the dataset's copies, is the DEPTH
                sensor's; the colour sensor is the nominal 525 camera
                (relocfw.core.camera.SEVENSCENES_COLOUR), or `colour_focal`'s.
                `intrinsics_for` names which sensor the file
                describes (default "depth"); the other sensor gets its nominal camera
                scaled to the colour images' size. The file is the scene folder's,
                else the dataset root's (the folder above it, where 7-Scenes' archives
                put it), sized like the first image of the split. Without a file: the
                nominal cameras for 640 x 480, without reading an image (so a copy
                scaled to another size needs its own file), with one note on stderr.
    depth_path  `frame-NNNNNN.depth.png` beside the colour image when it exists (16-bit,
                millimetres; copies without depth load as before, with None).
    depth_camera, depth_to_colour
                the depth sensor's camera and the Kinect's depth-to-colour transform
                (SEVENSCENES_DEPTH_TO_COLOUR): 7-Scenes' depth maps are the raw
                sensor's, not registered to the colour images, so lifting registers
                them first (relocfw.structure.registration). A scene folder (or the
                dataset root) holding `depth-registered.txt` declares its depth maps
                registered already (relocfw's synthetic scene writes one): the file
                is then the colour camera's and the frames get no depth camera.
    pose_to_colour
                which sensor the poses describe (`poses_of`). "colour" (the default)
                takes them as the colour camera's: None. "depth" takes them as the
                depth sensor's, which KinectFusion tracked: the frames then carry the
                depth-to-colour transform, and the structure refiners solve the colour
                camera and answer the depth sensor's pose (relocfw.core.sensor_poses).
                On Red Kitchen "depth" made positions worse on a validation block
                (docs/results/structure.md, "Which sensor the poses describe"), so it
                is not the default. Registered depth has no depth-to-colour transform:
                there the poses are always the colour camera's.
    pgt         a pseudo-ground-truth file (relocfw.data.pseudo_ground_truth: Brachmann
                et al.'s SfM or DSLAM poses of the colour camera) in place of the
                `.pose.txt` files: each frame's pose and colour camera (the line's
                focal length, principal point at the image centre) come from its line,
                matched by sequence and frame number; frames without a line are named
                in one note and left out. The depth camera and the depth-to-colour
                transform stay the Kinect's, so depth is registered into the colour
                image as without the file, now at the file's colour pose. `poses_of`,
                `colour_focal` and `intrinsics_for=colour` do not apply (refused).
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relocfw.core.camera import SEVENSCENES_COLOUR, SEVENSCENES_DEPTH, PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import pose_from_matrix
from relocfw.core.rigid import checked_rigid
from relocfw.core.values import Pose
from relocfw.data.depth import depth_path_of
from relocfw.data.frames import Frame
from relocfw.data.intrinsics import INTRINSICS_FILE, note_default_camera, read_camera_for_images
from relocfw.data.on_error import OnError
from relocfw.data.pseudo_ground_truth import PseudoGroundTruth, read_pseudo_ground_truth

SPLIT_FILES = {"train": "TrainSplit.txt", "test": "TestSplit.txt"}
SEQUENCE_LINE = re.compile(r"^sequence(\d+)$", re.IGNORECASE)
# The Kinect's two sensors: which one camera-intrinsics.txt describes
# (dataset.intrinsics_for), and which one the pose files describe (dataset.poses_of).
SENSORS = ("depth", "colour")
# A file whose presence in a scene folder (or the dataset root) says that its depth
# maps are registered to the colour images, pixel for pixel.
REGISTERED_MARKER = "depth-registered.txt"
# A file taken as the depth camera whose fx / width lies this close (relative) to the
# colour camera's 525 / 640 is probably a colour calibration (the depth
# sensor's is 585 / 640, 10% more).
COLOUR_LOOKALIKE_SHARE = 0.03
# Frames without a line in a pseudo-ground-truth file named in its note, the rest counted.
NAMED_MISSING = 20

# The Kinect's depth-to-colour transform, x_colour = R x_depth + t (metres): the
# calibration that DSAC* and ACE use on 7-Scenes (vislearn/dsacstar and nianticlabs/ace,
# datasets/setup_7scenes.py, `d_to_rgb`, taken from tsattler/visloc_pseudo_gt_limitations;
# they cite https://projet.liris.cnrs.fr/voir/activities-dataset/kinect-calibration.html):
# the colour sensor 2.56 cm along -x of the depth sensor, rotated by about 0.65 degrees.
SEVENSCENES_DEPTH_TO_COLOUR = checked_rigid(
    [
        [0.99996518012567637, 0.0026765126468950343, -0.0079041012313000904, -0.025558943178152542],
        [-0.00274093112813167, 0.99996302803027592, -0.0081504520778013286, 0.00010109636268061706],
        [0.0078819942130445332, 0.0081718328771890631, 0.99993554558014031, 0.0020318321729487039],
        [0.0, 0.0, 0.0, 1.0],
    ],
    "7-Scenes' Kinect depth-to-colour calibration",
)


def scene_folder(root: str | Path, scene: str | None) -> Path:
    """The folder holding the split files: `root/scene`, or `root` itself."""
    if root is None or str(root) == "":
        raise ConfigError("dataset.root is not set: pass dataset.root=DIR")
    root = Path(root).expanduser()
    if not root.is_dir():
        raise DataError(f"dataset.root: folder not found: {root}")
    folder = root / scene if scene else root
    if not folder.is_dir():
        available = sorted(p.name for p in root.iterdir() if (p / "TrainSplit.txt").is_file())
        raise DataError(
            f"dataset.scene: no scene {scene!r} in {root}"
            + (f" (found: {', '.join(available)})" if available else "")
        )
    return folder


def split_text(path: Path) -> str:
    """A split file's text; a byte that is not UTF-8 is a DataError naming the file
    and the byte's position (the file is likely damaged or not a split file)."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise DataError(
            f"{path}: not a text split file (byte {error.object[error.start]:#04x} at "
            f"offset {error.start} is not UTF-8)"
        ) from error


def read_split(path: Path) -> list[int]:
    """Sequence numbers listed in a TrainSplit.txt / TestSplit.txt file."""
    if not path.is_file():
        raise DataError(f"split file not found: {path}")
    numbers = []
    for number, line in enumerate(split_text(path).splitlines(), start=1):
        text = line.strip()
        if not text:
            continue
        match = SEQUENCE_LINE.match(text)
        if not match:
            raise DataError(f"{path}:{number}: expected a line like 'sequence1', got {text!r}")
        numbers.append(int(match.group(1)))
    if not numbers:
        raise DataError(f"{path}: lists no sequences")
    return numbers


def read_pose_file(path: Path) -> np.ndarray:
    """A 4x4 matrix from 7-Scenes' text format (tabs, CRLF, 3-digit exponents)."""
    if not path.is_file():
        raise DataError(f"pose file not found: {path}")
    try:
        values = [float(v) for v in path.read_text(encoding="utf-8").split()]
    except ValueError as error:  # UnicodeDecodeError included: it is a ValueError
        raise DataError(f"{path}: not a pose file ({error})") from error
    if len(values) != 16:
        raise DataError(f"{path}: expected 16 numbers (a 4x4 matrix), found {len(values)}")
    return np.array(values).reshape(4, 4)


def intrinsics_file(folder: Path) -> Path | None:
    """The camera-intrinsics.txt of a scene folder: its own, else the dataset root's.

    7-Scenes' archives keep one file for all scenes in the folder holding the scene
    folders; a file in the scene folder itself is more specific, so it wins.
    """
    for candidate in (folder / INTRINSICS_FILE, folder.parent / INTRINSICS_FILE):
        if candidate.is_file():
            return candidate
    return None


@dataclass(frozen=True)
class SceneCameras:
    """A scene's cameras: the colour images', and the depth maps' where they are not
    registered to the colour images (None where they are)."""

    colour: PinholeCamera
    depth: PinholeCamera | None
    depth_to_colour: np.ndarray | None


def sensor_named(key: str, value: object, described: str) -> str:
    """`value` when it names a sensor (SENSORS), else a ConfigError naming
    dataset.<key> and what the sensor is the one of (`described`)."""
    if value not in SENSORS:
        raise ConfigError(
            f"dataset.{key} must be one of {', '.join(SENSORS)} (the sensor {described}), "
            f"got {value!r}"
        )
    return str(value)


def checked_sensor(intrinsics_for: object) -> str:
    """dataset.intrinsics_for, checked."""
    return sensor_named("intrinsics_for", intrinsics_for, "camera-intrinsics.txt describes")


def checked_pose_sensor(poses_of: object) -> str:
    """dataset.poses_of, checked."""
    return sensor_named("poses_of", poses_of, "the pose files describe")


def depth_registered(folder: Path) -> bool:
    """Whether the scene folder or the dataset root declares registered depth."""
    return any((place / REGISTERED_MARKER).is_file() for place in (folder, folder.parent))


def note_colour_lookalike(path: Path, camera: PinholeCamera) -> None:
    """One line on stderr when `camera`, read from `path` as the depth camera, has the
    colour camera's focal length for its width: a colour calibration, most likely,
    which as the depth camera would register every depth map wrongly."""
    ratio = camera.fx / camera.width
    colour = SEVENSCENES_COLOUR.fx / SEVENSCENES_COLOUR.width
    if abs(ratio - colour) <= COLOUR_LOOKALIKE_SHARE * colour:
        print(
            f"note: {path}: fx={camera.fx:g} for {camera.width} px wide images looks like "
            f"the colour camera's ({SEVENSCENES_COLOUR.fx:g} for "
            f"{SEVENSCENES_COLOUR.width}), yet it is read as the depth camera; if the file "
            "describes the colour camera, set dataset.intrinsics_for=colour",
            file=sys.stderr,
        )


def colour_camera(colour_focal: object) -> PinholeCamera:
    """The 640 x 480 colour camera of focal length `colour_focal` (principal point
    SEVENSCENES_COLOUR's), or SEVENSCENES_COLOUR itself for None.

    Raises:
        ConfigError: naming dataset.colour_focal when it is not a positive number.
    """
    if colour_focal is None:
        return SEVENSCENES_COLOUR
    if isinstance(colour_focal, bool) or not isinstance(colour_focal, (int, float)):
        raise ConfigError(f"dataset.colour_focal must be a number of pixels, got {colour_focal!r}")
    focal = float(colour_focal)
    if not math.isfinite(focal) or focal <= 0:
        raise ConfigError(f"dataset.colour_focal must be a positive number of pixels, got {focal}")
    nominal = SEVENSCENES_COLOUR
    return PinholeCamera(focal, focal, nominal.cx, nominal.cy, nominal.width, nominal.height)


def scene_cameras(
    folder: Path,
    images: Sequence[Path],
    intrinsics_for: str = "depth",
    colour_focal: float | None = None,
    colour_given: bool = False,
) -> SceneCameras:
    """The cameras of a scene's images and depth maps.

    Args:
        folder: the scene folder.
        images: the colour images of the split, in order (the first that decodes
            gives the size a file's matrix belongs to).
        intrinsics_for: the sensor camera-intrinsics.txt describes, "depth" (as 7-Scenes'
            copies ship it) or "colour"; the other sensor gets its nominal camera
            scaled to the same size. Not used where the depth is registered.
        colour_focal: the colour camera's focal length (pixels at 640 x 480) where no
            file describes the colour camera; None: SEVENSCENES_COLOUR's.
        colour_given: the colour camera comes from elsewhere (a pseudo-ground-truth
            file's lines), so a missing file's note names only the depth camera.

    Raises:
        DataError: naming the intrinsics file when it is malformed.
        ConfigError: naming dataset.intrinsics_for when it is not a sensor, and
            dataset.colour_focal when it is not a positive number or a file
            describes the colour camera already.
    """
    intrinsics_for = checked_sensor(intrinsics_for)
    nominal_colour = colour_camera(colour_focal)
    registered = depth_registered(folder)
    path = intrinsics_file(folder)
    if colour_focal is not None and path is not None and (registered or intrinsics_for == "colour"):
        raise ConfigError(
            f"dataset.colour_focal={colour_focal:g}: {path} describes the colour camera "
            "already (it wins); leave colour_focal unset or the file out"
        )
    if path is None:
        if colour_given and not registered:
            note_default_camera(folder, SEVENSCENES_DEPTH, "7-Scenes' Kinect depth intrinsics")
        elif not colour_given:
            what = f"7-Scenes' Kinect colour intrinsics (fx=fy={nominal_colour.fx:g})"
            if not registered:
                what += " (depth: fx=fy=585)"
            note_default_camera(folder, nominal_colour, what)
        if registered:
            return SceneCameras(nominal_colour, None, None)
        return SceneCameras(nominal_colour, SEVENSCENES_DEPTH, SEVENSCENES_DEPTH_TO_COLOUR)
    from_file = read_camera_for_images(path, images)
    if registered:
        return SceneCameras(from_file, None, None)
    # Both sensors are taken to give images of the colour images' size (640 x 480 in
    # 7-Scenes); a copy resized to another size scales the nominal camera with it.
    size = (from_file.width, from_file.height)
    if intrinsics_for == "depth":
        note_colour_lookalike(path, from_file)
        return SceneCameras(nominal_colour.scaled_to(*size), from_file, SEVENSCENES_DEPTH_TO_COLOUR)
    return SceneCameras(from_file, SEVENSCENES_DEPTH.scaled_to(*size), SEVENSCENES_DEPTH_TO_COLOUR)


def frame_number(stem: str) -> int | None:
    """The number of a frame named `frame-000123`; None for another name."""
    digits = stem.rsplit("-", 1)[-1]
    return int(digits) if digits.isascii() and digits.isdigit() else None


def centred_camera(focal: float, width: int, height: int) -> PinholeCamera:
    """The colour camera a pseudo-ground-truth line describes: focal length `focal`
    for images of this size, the principal point at the image centre (width / 2,
    height / 2, as 7-Scenes' nominal cameras have it)."""
    return PinholeCamera(focal, focal, width / 2, height / 2, width, height)


def note_missing_lines(path: Path, missing: Sequence[str], kept: int) -> None:
    """One note on stderr naming the frames a pseudo-ground-truth file has no line for
    (left out: a frame without a reference pose can be neither mapped nor scored)."""
    named = ", ".join(missing[:NAMED_MISSING])
    more = f" and {len(missing) - NAMED_MISSING} more" if len(missing) > NAMED_MISSING else ""
    print(
        f"note: {path} (dataset.pgt) has no line for {len(missing)} frame(s) of the split, "
        "left out "
        f"({kept} kept): {named}{more}",
        file=sys.stderr,
    )


def existing_depth(image: Path) -> Path | None:
    """The depth map beside a colour image, or None when there is none."""
    path = depth_path_of(image)
    return path if path.is_file() else None


def sequence_images(seq_dir: Path, source: str) -> list[Path]:
    """The colour images of one sequence folder in frame order (PNG, else JPEG).

    Args:
        seq_dir: `seq-XX`.
        source: what named the sequence (the split file or the option), for errors.
    """
    if not seq_dir.is_dir():
        raise DataError(f"{source}: sequence folder not found: {seq_dir}")
    images = sorted(seq_dir.glob("frame-*.color.png")) or sorted(seq_dir.glob("frame-*.color.jpg"))
    if not images:
        raise DataError(f"no frame-*.color.png or .jpg images in {seq_dir}")
    return images


def load_sevenscenes(
    root: str | Path,
    scene: str | None,
    split: str,
    on_error: OnError | None = None,
    sequences: Sequence[int] | None = None,
    intrinsics_for: str = "depth",
    poses_of: str = "colour",
    colour_focal: float | None = None,
    reference: PseudoGroundTruth | None = None,
) -> list[Frame]:
    """Frames of one split, in sequence then frame order, with cameras and depth path.

    Args:
        root: dataset folder (the one holding scene folders), or a scene folder.
        scene: scene name such as "chess"; None when `root` is the scene folder.
        split: "train" or "test".
        on_error: what to do with a bad pose file (default: fail).
        sequences: sequence numbers to use instead of the split file's, e.g. to hold
            out a validation block of the training sequences.
        intrinsics_for: the sensor camera-intrinsics.txt describes, "depth" or
            "colour" (scene_cameras).
        poses_of: the sensor the pose files describe, "colour" or "depth"; with
            "depth" and unregistered depth each frame's `pose_to_colour` is the
            depth-to-colour transform (see the module).
        colour_focal: the colour camera's focal length (pixels at 640 x 480) where no
            file describes it; None: SEVENSCENES_COLOUR's (scene_cameras).
        reference: a pseudo-ground-truth file (read_pseudo_ground_truth), read
            instead of the `.pose.txt` files: each frame's pose and colour camera come
            from its line; frames without one are named in one note on stderr and
            left out (see the module).

    Raises:
        DataError: a missing split file, sequence folder or image set, a bad pose file
            (under on_error=fail), or a malformed camera-intrinsics.txt (always: it
            concerns every frame), each naming the file.
        ConfigError: naming dataset.intrinsics_for or dataset.poses_of when it is not
            depth or colour.
    """
    intrinsics_for = checked_sensor(intrinsics_for)
    poses_of = checked_pose_sensor(poses_of)
    on_error = on_error or OnError()
    if split not in SPLIT_FILES:
        raise ConfigError(f"split must be 'train' or 'test', got {split!r}")
    folder = scene_folder(root, scene)
    source = f"dataset.{split}_sequences"
    if sequences is None:
        source = str(folder / SPLIT_FILES[split])
        sequences = read_split(folder / SPLIT_FILES[split])
    posed: list[tuple[str, Path, Pose]] = []
    focals: dict[str, float] = {}  # a frame's colour focal length from `reference`
    missing: list[str] = []  # frames without a line in `reference`
    for sequence in sequences:
        seq_dir = folder / f"seq-{sequence:02d}"
        for image in sequence_images(seq_dir, source):
            stem = image.name.split(".")[0]
            name = f"{seq_dir.name}/{stem}"
            if reference is not None:
                number = frame_number(stem)
                line = None if number is None else reference.get(sequence, number)
                if line is None:
                    missing.append(name)
                    continue
                posed.append((name, image, line.pose))
                focals[name] = line.focal
                continue
            pose_path = seq_dir / f"{stem}.pose.txt"
            try:
                pose = pose_from_matrix(read_pose_file(pose_path), source=str(pose_path))
            except DataError as error:
                on_error.handle(error)
                continue
            posed.append((name, image, pose))
    if missing:
        note_missing_lines(reference.path, missing, len(posed))
    if not posed:  # every pose skipped: nothing to give a camera to
        return []
    # One pair of cameras for the scene: 7-Scenes' frames all come from one Kinect.
    cameras = scene_cameras(
        folder, [image for _, image, _ in posed], intrinsics_for, colour_focal, bool(focals)
    )
    pose_to_colour = cameras.depth_to_colour if poses_of == "depth" else None
    reference_cameras: dict[float, PinholeCamera] = {}
    frames = []
    for name, image, pose in posed:
        colour = cameras.colour
        if name in focals:
            colour = reference_cameras.setdefault(
                focals[name], centred_camera(focals[name], colour.width, colour.height)
            )
        # The depth sensor's camera is the Kinect's whether or not this copy has
        # the frame's depth map.
        frames.append(
            Frame(
                name,
                image,
                pose,
                camera=colour,
                depth_path=existing_depth(image),
                depth_camera=cameras.depth,
                depth_to_colour=cameras.depth_to_colour,
                pose_to_colour=pose_to_colour,
            )
        )
    return frames


class SevenScenes:
    """A 7-Scenes scene as a dataset: `root/scene` with its split files.

    Args:
        root: the folder holding scene folders (or the scene folder, with scene=None).
        scene: scene name, e.g. "chess".
        on_error: "fail" or "skip" (bad files left out and listed).
        train_sequences: sequence numbers that replace TrainSplit.txt (None: the file).
        test_sequences: sequence numbers that replace TestSplit.txt (None: the file).
        intrinsics_for: the sensor camera-intrinsics.txt describes: "depth" (7-Scenes'
            own calibration, as its copies ship it) or "colour".
        poses_of: the sensor the pose files describe: "colour" or "depth" (see the
            module).
        colour_focal: the colour camera's focal length (pixels at 640 x 480) where no
            file describes it; None: SEVENSCENES_COLOUR's (525).
        pgt: a pseudo-ground-truth file whose poses and colour cameras replace the
            `.pose.txt` files and the nominal colour camera (see the module), or None.
    """

    def __init__(
        self,
        root: str | None = None,
        scene: str | None = None,
        on_error: str = "fail",
        train_sequences: Sequence[int] | None = None,
        test_sequences: Sequence[int] | None = None,
        intrinsics_for: str = "depth",
        poses_of: str = "colour",
        colour_focal: float | None = None,
        pgt: str | None = None,
    ) -> None:
        self.intrinsics_for = checked_sensor(intrinsics_for)
        colour_camera(colour_focal)  # checked before any file is read
        self.colour_focal = colour_focal
        self.poses_of = checked_pose_sensor(poses_of)
        check_pgt_options(pgt, self.poses_of, colour_focal, self.intrinsics_for)
        self.folder = scene_folder(root, scene)
        self.reference = None if pgt is None else read_pseudo_ground_truth(pgt_path(pgt))
        self.on_error = OnError(on_error)
        self.sequences = {
            "train": checked_sequences("train_sequences", train_sequences),
            "test": checked_sequences("test_sequences", test_sequences),
        }
        # The effective lists, a split file standing in for the list not given (a
        # missing split file is reported when its split is loaded).
        effective = {split: self.effective_sequences(split) for split in SPLIT_FILES}
        train, test = effective["train"], effective["test"]
        if train is not None and test is not None and set(train) & set(test):
            raise ConfigError(
                f"{self.split_source('train')} and {self.split_source('test')}: train "
                f"{train} and test {test} share {sorted(set(train) & set(test))}: a test "
                "frame would be in the map"
            )
        if self.reference is not None:
            for split, sequences in effective.items():
                check_reference_covers(self.reference, sequences, self.split_source(split))

    def effective_sequences(self, split: str) -> list[int] | None:
        """The split's sequence numbers: the option's, else its split file's, else None
        (no split file: loading the split says so)."""
        chosen = self.sequences[split]
        if chosen is not None:
            return chosen
        path = self.folder / SPLIT_FILES[split]
        return read_split(path) if path.is_file() else None

    def frames(self, split: str) -> list[Frame]:
        return load_sevenscenes(
            self.folder,
            None,
            split,
            self.on_error,
            self.sequences.get(split),
            self.intrinsics_for,
            self.poses_of,
            self.colour_focal,
            self.reference,
        )

    def split_source(self, split: str) -> str:
        """What lists the split's frames, for messages: the option or the split file."""
        chosen = self.sequences.get(split)
        if chosen is not None:
            return f"dataset.{split}_sequences={chosen} in {self.folder}"
        return str(self.folder / SPLIT_FILES[split])


def checked_sequences(key: str, values: Sequence[int] | None) -> list[int] | None:
    """A non-empty list of positive sequence numbers, or None (use the split file)."""
    if values is None:
        return None
    if isinstance(values, (str, int)) or not values:
        raise ConfigError(f"dataset.{key} must be a non-empty list such as [1, 3], got {values!r}")
    numbers = []
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"dataset.{key}: sequence numbers are integers >= 1, got {value!r}")
        numbers.append(value)
    return numbers


def pgt_path(pgt: object) -> Path:
    """dataset.pgt as a path; a ConfigError for anything but a non-empty string."""
    if not isinstance(pgt, (str, Path)) or str(pgt) == "":
        raise ConfigError(f"dataset.pgt must be the path of a pose file, got {pgt!r}")
    return Path(pgt).expanduser()


def check_pgt_options(
    pgt: object, poses_of: str, colour_focal: object, intrinsics_for: str
) -> None:
    """Refuse the options a pseudo-ground-truth file makes meaningless, naming them:
    its poses are the colour camera's (poses_of), its lines give the colour camera's
    focal length (colour_focal), and so camera-intrinsics.txt can only be the depth
    camera's (intrinsics_for)."""
    if pgt is None:
        return
    clashes = []
    if poses_of != "colour":
        clashes.append(f"dataset.poses_of={poses_of} (the file's poses are the colour camera's)")
    if colour_focal is not None:
        clashes.append(
            f"dataset.colour_focal={colour_focal} (each line gives the colour camera's "
            "focal length)"
        )
    if intrinsics_for != "depth":
        clashes.append(
            f"dataset.intrinsics_for={intrinsics_for} (the file gives the colour camera; "
            "camera-intrinsics.txt can only describe the depth camera)"
        )
    if clashes:
        raise ConfigError(
            f"dataset.pgt={pgt} does not go with " + " or ".join(clashes) + ": leave it out"
        )


def check_reference_covers(
    reference: PseudoGroundTruth, sequences: Sequence[int] | None, source: str
) -> None:
    """Refuse, before anything is trained, a pseudo-ground-truth file without a single
    line for one of a split's sequences: that split would lose the whole sequence (a
    file of only the training or only the test frames, as the published
    `*_train.txt` / `*_test.txt` files are)."""
    absent = [number for number in sequences or () if not reference.has_sequence(number)]
    if absent:
        raise DataError(
            f"{reference.path} (dataset.pgt) has no line for sequence(s) {absent} of "
            f"{source}; where the reference comes as separate train and test files, "
            "join them into one (cat TRAIN TEST > FILE)"
        )
