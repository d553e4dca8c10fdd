"""Recordings the mapper can replay, read into one form: a time-ordered stream of samples, each a
camera frame with the navigation state at its capture time (docs/replay.md).

Four layouts are read:

* ``companion``: the service's own ``--record`` folder (``meta.yaml``, ``frames.csv``,
  ``frames/``, ``telemetry.tlog``; docs/cameras.md). Navigation is rebuilt from the telemetry log
  exactly as the autopilot link builds it live (:class:`TelemetryNav`).
* ``tum``: a folder of images with camera poses in TUM trajectory format
  (``timestamp tx ty tz qx qy qz qw``, camera-to-world, OpenCV camera axes) plus ``camera.yaml``
  (intrinsics, OpenCV distortion, size) and ``meta.yaml`` (the world's up axis, metric scale,
  pose uncertainty). ``pose_sigmas.txt`` gives per-frame uncertainty when present.
* ``euroc``: the EuRoC MAV layout (``mav0/cam0/data.csv``, ``mav0/cam0/sensor.yaml``,
  ``mav0/state_groundtruth_estimate0/data.csv``).
* ``colmap``: a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``, in the folder
  or ``sparse/0``) with its ``images/`` and a ``meta.yaml`` (up direction, scale) and the images'
  times (``timestamps.txt`` or ``frame_interval_s``).

Pose-given layouts (tum, euroc, colmap) are converted to the project's frames (docs/conventions.md):
world -> local NED by :class:`WorldFrame` (north = a declared world direction, down = -up, east =
down x north, positions times the metric scale); the OpenCV camera frame (x right, y down, z
optical) -> the paper camera frame (x optical, y right, z down) by ``PAPER_TO_OPENCV``. The
camera pose is then written as a body pose for a mount (identity by default, so the body *is*
the camera and the declared uncertainty applies to the camera pose exactly):
``R_nb = R_nc R_bc^T``, ``p = p_c - R_nb t_bc`` (:func:`body_pose_from_camera`), which
``CameraMount.camera_pose`` maps back exactly.

Damage never stops a replay: a malformed line in any text file is skipped and counted
(:class:`RecordingStats`), a missing or undecodable image yields a sample without a frame, a frame
time the navigation cannot cover yields a sample without navigation (with the reason), corrupt
telemetry bytes are skipped by pymavlink's tlog reader and counted. Files that make the whole
recording meaningless (no camera model, no image list, no poses) raise :class:`RecordingError`
naming the file and what is wrong.

The modules:

* :mod:`~companion.desk.recordings.layouts` - which layout a folder holds; :func:`open_recording`;
* :mod:`~companion.desk.recordings.recording` - the interface (:class:`Recording`, :class:`Sample`),
  the frame conversions and what every reader shares;
* :mod:`~companion.desk.recordings.poses` - pose tables of the pose-given layouts;
* :mod:`~companion.desk.recordings.telemetry`, :mod:`~companion.desk.recordings.tum`,
  :mod:`~companion.desk.recordings.euroc`, :mod:`~companion.desk.recordings.colmap` - the four
  layouts (TUM and COLMAP also written, by ``--export-tum`` and ``--export-colmap``).
"""
