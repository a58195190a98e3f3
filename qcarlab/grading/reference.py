"""The reference's submission: what a student who did every lab right hands in, for the sheets'
self-check (``qcarlab labs check``) and the grading tests.

For each lab sheet a folder as ``qcarlab template`` makes it, with every choice filled with
qcarlab's value (``params.yaml``) and block files that call qcarlab's reference blocks. A graded
block that imports qcarlab's own block of its name is refused (the grader reads the imports);
these stand-ins load it with ``importlib`` instead, which that check does not see (the threat model in
docs/explanation/grading-sandbox.md says so): the self-check needs a right answer, not an honest student.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

from qcarlab.experiments.labs import find_lab, params_file, write_template

# sheet -> {file: source}: the reference blocks, with the signatures the template asks for
REFERENCE = {
    "basic-io": {
        "basic_speed_estimation.py": """
            _reference = __import__("importlib").import_module("qcarlab.control.speed").basic_speed_estimation

            def basic_speed_estimation(counts_per_s):
                return _reference(counts_per_s)
        """,
    },
    "path-following": {
        "pure_pursuit.py": """
            from qcarlab.constants import DEFAULT_PARAMS
            _reference = __import__("importlib").import_module("qcarlab.control.steering").pure_pursuit

            def pure_pursuit(pose, target, lookahead, wheelbase):
                return _reference(pose, target, lookahead, wheelbase, max_steering=DEFAULT_PARAMS.max_steering)
        """,
        "speed_controller.py": """
            from qcarlab.control.speed import SpeedController

            class speed_controller:
                def __init__(self):
                    self.reset()

                def reset(self):
                    self._pi = SpeedController()

                def __call__(self, v_ref, v_measured, dt):
                    return self._pi(v_ref, v_measured, dt)
        """,
    },
    "stop-sign": {
        "stop_sign.py": """
            def stop_sign(distance_to_sign, desired_speed):
                return 0.0 if 0.05 < distance_to_sign < 0.40 else desired_speed
        """,
        "red_share.py": """
            _reference = __import__("importlib").import_module("qcarlab.perception.stop_signs").red_share

            def red_share(image_bgr, circle):
                return _reference(image_bgr, circle)
        """,
        "stop_sign_hold.py": """
            _reference = __import__("importlib").import_module("qcarlab.control.stop_sign").StopSignHold

            class stop_sign_hold:
                def __init__(self):
                    self.reset()

                def reset(self):
                    self._hold = _reference()

                @property
                def state(self):
                    return self._hold.state

                def __call__(self, t, distance_to_sign, new_frame, speed, desired_speed):
                    return self._hold(t, distance_to_sign, new_frame, speed, desired_speed)
        """,
    },
    "obstacle-avoidance": {
        "lidar_stop.py": """
            _reference = __import__("importlib").import_module("qcarlab.control.lidar_avoid").lidar_stop

            def lidar_stop(distances, headings, desired_speed):
                return _reference(distances, headings, desired_speed)
        """,
        "lidar_steer.py": """
            _reference = __import__("importlib").import_module("qcarlab.control.lidar_avoid").lidar_steer

            def lidar_steer(distances, headings, desired_speed):
                return _reference(distances, headings, desired_speed)
        """,
        "lidar_avoid.py": """
            LidarAvoid = __import__("importlib").import_module("qcarlab.control.lidar_avoid").LidarAvoid

            class lidar_avoid:
                def __init__(self):
                    self.reset()

                def reset(self):
                    self._avoid = LidarAvoid()

                @property
                def state(self):
                    return self._avoid.state

                def __call__(self, distances, headings, desired_speed):
                    return self._avoid(distances, headings, desired_speed)
        """,
    },
    "lane-following": {},
}
LAB_OF = {"basic-io": "io-test", "path-following": "path-follow", "stop-sign": "stop-sign",
          "obstacle-avoidance": "avoid", "lane-following": "lane-follow"}


def write_block(folder: Path, filename: str, source: str) -> Path:
    """``folder/filename`` with ``source`` (dedented)."""
    path = Path(folder) / filename
    path.write_text(textwrap.dedent(source).lstrip(), encoding="utf-8")
    return path


def reference_submission(root: Path, sheets: tuple[str, ...] = tuple(REFERENCE)) -> Path:
    """ROOT/SHEET/ for each sheet: the template with qcarlab's choices in params.yaml, the reference
    blocks, answers.md answered."""
    root = Path(root)
    for sheet in sheets:
        folder = root / sheet
        lab = find_lab(LAB_OF[sheet])
        write_template(lab, folder, force=True)
        (folder / "README.md").unlink(missing_ok=True)
        (folder / "params.yaml").write_text(params_file(lab, filled=True), encoding="utf-8")
        for filename, source in REFERENCE[sheet].items():
            write_block(folder, filename, source)
        (folder / "answers.md").write_text(f"# {sheet}\n\nMy answers for {sheet}.\n", encoding="utf-8")
    return root


__all__ = ["LAB_OF", "REFERENCE", "reference_submission", "write_block"]
