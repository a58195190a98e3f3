"""The labs a student does: each one's model, tunables, questions, and the workspace template.

    qcarlab blocks stop-sign                  # the lab's blocks: signature, units, sheet section
    qcarlab template stop-sign --out mylab    # mylab/stop_sign.py, params.yaml, answers.md, README.md

A lab is found by its command (``stop-sign``), its sheet's name (``stop-sign``, ``path-following``)
or its section (``5.2``). The template writes one Python file per block the sheet asks the
student to fill (each with the sheet's signature, the task text, units and section, and a body
that raises ``NotImplementedError`` until it is written), ``params.yaml`` with the lab's
tunables in a ``lab:`` section, and ``answers.md`` with the sheet's questions for the section.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from qcarlab.blocks import BlockSpec
from qcarlab.errors import InputError
from qcarlab.experiments.avoid import AvoidConfig, AvoidLab
from qcarlab.experiments.io_test import BasicIOLab
from qcarlab.experiments.lane_follow import LaneFollowConfig, LaneFollowingLab
from qcarlab.experiments.model import LabModel
from qcarlab.experiments.path_follow import FollowConfig, PathFollowingLab
from qcarlab.experiments.stop_sign import StopSignConfig, StopSignLab


class Choice(NamedTuple):
    """A tunable the student chooses (the template leaves it empty; the sheet's tasks grade it)."""

    name: str
    task: str  # the sheet's task, as the template's comment says it
    reference: Any = None  # the reference's choice (None: the lab's default)


@dataclass(frozen=True)
class Lab:
    """One lab of the sheet as the student meets it."""

    command: str  # the subcommand
    sheet: str  # the lab sheet's name in labs/
    section: str
    title: str
    model: type[LabModel]
    config: type | None  # the run's config dataclass (its fields are the tunables)
    tunables: tuple[str, ...]  # the fields params.yaml offers
    questions: tuple[str, ...]  # the sheet's "explain" tasks, for answers.md
    run: str  # how to run the lab with the workspace, from inside it
    choose: tuple[Choice, ...] = ()  # the tunables the student chooses: the template leaves them empty

    @property
    def blocks(self) -> tuple[BlockSpec, ...]:
        return self.model.BLOCKS

    @property
    def to_fill(self) -> tuple[BlockSpec, ...]:
        return tuple(b for b in self.blocks if b.fill)

    def defaults(self) -> dict[str, Any]:
        if self.config is None:
            return {}
        cfg = self.config()
        out = {}
        for name in self.tunables:
            value = getattr(cfg, name)
            out[name] = list(value) if isinstance(value, tuple) else value
        return out


LABS: tuple[Lab, ...] = (
    Lab("io-test", "basic-io", "3.3", "Basic I/O", BasicIOLab, None, (),
        ("Task 2: Explain all the outputs (encoder counts, tachometer, motor current, battery voltage, gyro, "
         "accelerometer). What does each measure, in which unit?",
         "Task 2: Verify the battery voltage the program reports against the car's display. Is it charged?",
         "How far did the wheels turn according to your basic_speed_estimation, and does it match the "
         "encoder counts?"),
        "qcarlab io-test --use basic_speed_estimation.py --throttle 0.1 --duration 2"),
    Lab("path-follow", "path-following", "4", "Path following", PathFollowingLab, FollowConfig,
        ("lookahead", "speed", "kp", "ki", "kff"),
        ("4.1.1: In the bicycle model, which is the local frame and which the global one? Which is the "
         "steering angle, which the heading? What is the difference between them? Express the yaw rate r.",
         "4.2.2 Task 1: Follow p1 (the line). What happens? Is the path followed precisely?",
         "4.2.2 Task 2: The same with p2, p3 and p4: where does each go wrong, and why?",
         "4.2.2 Tasks 3-4: Which look-ahead distance did you choose for p4, and why is the behaviour better?",
         "4.2.3 Task 1: Study the speed controller's structure. What kind of controller is it?",
         "4.2.3: Which K_p and K_i did you choose for the best speed control? Explain how and why."),
        "qcarlab path-follow butterfly --size 2 --use . --params params.yaml",
        (Choice("lookahead", "4.2.2 Tasks 3-4: the look-ahead distance you chose for p4, m (try a sweep: "
                "--lookahead 0.2,0.3,0.5,0.8)", 0.5),)),
    Lab("stop-sign", "stop-sign", "5.2", "Stop at a stop sign", StopSignLab, StopSignConfig,
        ("speed", "near", "far", "kp", "ki", "kff", "hsv_min", "hsv_max", "min_area"),
        ("5.1: Explain what each block of the RGBD Imaging model does (thresholding, find objects, distance).",
         "5.2 Task 3: Place the car at least 1 m before the sign. Where did it stop, and was that what you "
         "wanted?",
         "5.2 Task 4: Suggest improvements to the stopSign block (think of other speeds, a sign lost from "
         "view, driving on after the stop)."),
        "qcarlab stop-sign --use . --params params.yaml",
        (Choice("hsv_min", "5.1: the lower HSV bound of the sign's red, [H, S, V] (H in OpenCV's 0..179 = deg / 2; "
          "red's hue is 0, so a range may wrap: H_min > H_max)"),
         Choice("hsv_max", "5.1: the upper HSV bound of the sign's red, [H, S, V]"))),
    Lab("lane-follow", "lane-following", "5.3", "Vision lane following", LaneFollowingLab, LaneFollowConfig,
        ("hsv_min", "hsv_max", "speed", "speed_selector", "lookahead", "stop_distance", "stop_offset",
         "distance_to_lane", "kp", "ki", "kff", "white_backup", "white_s_max", "white_v_min"),
        ("5.3 Task: Which HSV ranges did you choose so that only the yellow line is detected? How did you "
         "check them at different spots of the track (the brightness changes)?",
         "What happens when the yellow line leaves the camera's view in a tight curve?"),
        "qcarlab lane-follow --params params.yaml --laps 1",
        (Choice("hsv_min", "5.3.2: the lower HSV bound of the yellow centre line, [H, S, V] (H in OpenCV's "
          "0..179 = deg / 2); tune it with qcarlab lane-follow --hsv-tune"),
         Choice("hsv_max", "5.3.2: the upper HSV bound of the yellow centre line, [H, S, V]"))),
    Lab("avoid", "obstacle-avoidance", "6.1", "LIDAR obstacle detection and avoidance", AvoidLab, AvoidConfig,
        ("speed", "stop_distance", "half_width", "kp", "ki", "kff"),
        ("Task 2: Run the stop strategy with an obstacle ahead. Describe the car's behaviour.",
         "Task 3: Run the steering strategy. Describe the car's behaviour; when does it fail?",
         "Task 4 (open problem): How does your lidar_avoid combine the two? When does it stop, when does it "
         "steer, and how does it avoid contact?"),
        "qcarlab avoid --strategy student --use . --params params.yaml"),
)

_ALIASES = {"basic-io": "io-test", "3.3": "io-test", "path-following": "path-follow", "4": "path-follow",
            "4.2": "path-follow", "5.2": "stop-sign", "5.1": "stop-sign", "lane-following": "lane-follow",
            "5.3": "lane-follow", "obstacle-avoidance": "avoid", "6.1": "avoid", "6": "avoid"}


def find_lab(name: str) -> Lab:
    """The lab for a command, sheet name or section; one line listing them when unknown."""
    key = _ALIASES.get(name, name)
    for lab in LABS:
        if lab.command == key:
            return lab
    known = ", ".join(f"{lab.command} ({lab.section})" for lab in LABS)
    raise InputError(f"unknown lab {name!r}; the labs with blocks: {known}")


# --------------------------------------------------------------------------------------------
# the student's workspace
# --------------------------------------------------------------------------------------------
def _wrap(text: str, indent: str = "", width: int = 96) -> str:
    import textwrap

    return textwrap.fill(text, width=width, initial_indent=indent, subsequent_indent=indent)


def block_file(spec: BlockSpec, lab: Lab) -> str:
    """The template of one block: the sheet's signature and task, a body that says it is not filled in."""
    args = ", ".join(spec.params)
    doc = [f'"""Sheet {spec.section}: the {spec.name} block ({lab.title}).', "",
           _wrap(spec.fill or spec.doc), "",
           f"    {spec.signature}", f"    units: {spec.units}"]
    if spec.example:
        doc.append(f"    e.g. {spec.example}")
    doc += ["", "Conventions: SI units; body frame x forward, y left; angles counter-clockwise, + = left."]
    if "headings" in args:
        doc += ["LIDAR headings: rad, 0 straight ahead, + to the left, - to the right, in (-pi, pi] (behind: +-pi);",
                "distances: m, 0 = no return on that beam; both numpy arrays of one value per beam."]
    doc += [f"Run it:  {lab.run}", f"(the reference block it replaces: qcarlab blocks {lab.command})", '"""', ""]
    stub = f'raise NotImplementedError("{spec.name} is not filled in yet (sheet {spec.section})")'
    if spec.stateful:
        body = [
            "", "",
            f"class {spec.name}:",
            '    """A class, because this block keeps a state between calls. qcarlab makes one per run',
            '    (no arguments), calls reset() at the start, then calls the object every tick."""',
            "",
            "    def __init__(self):",
            "        self.reset()",
            "",
            "    def reset(self):",
            "        pass  # set your state here (e.g. an integral, a state machine's state)",
            "",
            f"    def __call__(self, {args}):",
            "        " + stub,
        ]
    else:
        body = ["", "", f"def {spec.name}({args}):", "    " + stub]
    imports = ["import math", "", "import numpy as np"] if "distances" in args else ["import math"]
    return "\n".join(doc + imports + body) + "\n"


def params_file(lab: Lab, filled: bool = False) -> str:
    """The template's params.yaml: the lab's tunables with qcarlab's values, the student's choices
    (``lab.choose``) empty; ``filled``: those with qcarlab's values too (the reference's submission)."""
    lines = [f"# Your tunables for sheet {lab.section} ({lab.title}): qcarlab {lab.command} --params params.yaml",
             "# Options typed on the command line win over this file. Units: SI (m, m/s, rad); HSV as OpenCV's",
             "# H 0..179 (degrees / 2), S and V 0..255. The simulated car's own parameters may go at the top",
             "# level (see qcarlab/constants.py); the lab's go under lab:."]
    defaults = lab.defaults()
    if not defaults:
        lines.append("lab: {}")
        return "\n".join(lines) + "\n"
    lines.append("lab:")
    chosen = {c.name for c in lab.choose}
    for c in lab.choose if not filled else ():  # the student's choices first, empty: the sheet's tasks grade them
        lines += [f"  # {line}" for line in _wrap(f"yours to choose: {c.task}", width=94).splitlines()]
        lines.append(f"  {c.name}:   # empty until you fill it in (runs with --params refuse it empty)")
    reference = {c.name: c.reference for c in lab.choose if c.reference is not None} if filled else {}
    for name, value in defaults.items():
        if name in chosen and not filled:
            continue
        lines.append(f"  {name}: {_yaml_value(reference.get(name, value))}")
    return "\n".join(lines) + "\n"


def _yaml_value(value: Any) -> str:
    """A tunable's value as params.yaml writes it."""
    if isinstance(value, list):
        return "[" + ", ".join(str(v) for v in value) + "]"
    if isinstance(value, float) and math.isfinite(value):
        return repr(value)
    if value is None:
        return "null"
    return str(value).lower() if isinstance(value, bool) else str(value)


def answers_file(lab: Lab) -> str:
    out = [f"# Sheet {lab.section}: {lab.title}: your answers", ""]
    for i, q in enumerate(lab.questions, 1):
        out += [f"## {i}. {q}", "", "_Your answer._", ""]
    return "\n".join(out)


OTHER_BLOCKS = "other-blocks"  # the template's folder of the blocks the sheet does not ask to fill


def readme_file(lab: Lab) -> str:
    files = "".join(f"- `{b.name}.py`: {b.doc}\n" for b in lab.to_fill)
    others = [b for b in lab.blocks if not b.fill]
    if others:
        files += (f"- `{OTHER_BLOCKS}/`: the lab's other blocks ({', '.join(b.name for b in others)}) as templates: "
                  "to replace one with yours, move its file up into this folder, fill it in and run with `--use .`.\n")
    return (f"# Sheet {lab.section}: {lab.title}\n\n"
            f"Fill in the blocks, tune `params.yaml`, answer `answers.md`.\n\n{files}"
            "- `params.yaml`: the lab's tunables.\n- `answers.md`: the sheet's questions.\n\n"
            f"Run the lab with your blocks, from this folder:\n\n    {lab.run}\n\n"
            f"Grade yourself as the teacher will, from this folder:\n\n    qcarlab grade {lab.sheet} --submission .\n\n"
            f"`qcarlab blocks {lab.command}` lists every block of the lab; any of them can be yours: "
            "a function (or class) in a .py file here, named like the block.\n")


def write_template(lab: Lab, out: str | Path, force: bool = False) -> list[Path]:
    """Write the student's workspace for ``lab`` into ``out``; refuse to overwrite without ``force``."""
    folder = Path(out)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--out {folder}: exists and is not a folder")
    files = {f"{b.name}.py": block_file(b, lab) for b in lab.to_fill}
    # every other block of the lab, for a student who wants to replace it too: copy it up a level
    files.update({f"{OTHER_BLOCKS}/{b.name}.py": block_file(b, lab) for b in lab.blocks if not b.fill})
    files.update({"params.yaml": params_file(lab), "answers.md": answers_file(lab), "README.md": readme_file(lab)})
    clash = [name for name in files if (folder / name).exists()]
    if clash and not force:
        raise InputError(f"--out {folder}: would overwrite {', '.join(clash)} (your work?); use --force to replace")
    written = []
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            path = folder / name
            path.parent.mkdir(exist_ok=True)
            path.write_text(text, encoding="utf-8")
            written.append(path)
    except OSError as exc:
        raise InputError(f"--out {folder}: cannot write the workspace there ({exc.strerror or exc})") from None
    return written


def block_rows(lab: Lab) -> list[dict[str, Any]]:
    """The lab's blocks as rows (for ``qcarlab blocks`` and its --json)."""
    return [{"name": b.name, "signature": b.signature, "units": b.units, "section": b.section, "what": b.doc,
             "stateful": b.stateful, "in_template": bool(b.fill)} for b in lab.blocks]


__all__ = ["LABS", "Choice", "Lab", "block_rows", "find_lab", "write_template"]
