"""The index of qcarlab's commands: name, the module that defines it, the first paragraph of its
help. ``qcarlab --help`` lists the commands from here without importing their modules (issue 28:
the bare help in a fraction of the time); any other call imports the modules (:func:`qcarlab.cli.load_commands`).
``tests/test_cli_index.py`` fails when this file and the commands disagree, and prints the file
as it should be."""

from __future__ import annotations

#: the command modules, in the order they register their commands
MODULES = ('io_test', 'net', 'drive', 'paths', 'sensors', 'stop_sign', 'lane_follow', 'avoid', 'grade', 'lab', 'replay', 'onboard', 'detect', 'warmstart')

#: (name, module, the first paragraph of its help), in the order ``qcarlab --help`` lists them
COMMANDS = (
    ('io-test', 'io_test',
     'Basic I/O test (sheet 3.3): hold throttle, steering and lamps; read encoder, current, battery, IMU.'),
    ('serve', 'net',
     'Serve a car over TCP: the simulator (real time, or --lockstep) or the physical QCar.'),
    ('ping', 'net',
     'Round-trip latency, loss and identity of a car (sheet 3.1); exit 0 when it answers, 1 otherwise.'),
    ('keyboard-drive', 'drive',
     'Drive the car from the keyboard (sheet 3.4) with a live panel: speed, steering, battery, nearest obstacle, map.'),
    ('path-gen', 'paths',
     'Generate a reference path (sheet 4.2.1): the line p1, the circle p2, the butterflies p3/p4.'),
    ('path-follow', 'paths',
     'Follow a path with pure pursuit (or carrot, stanley) and the feed-forward PI speed controller.'),
    ('lidar-scan', 'sensors',
     'Capture LIDAR scans (sheet 3.5): nearest obstacle, range, polar plot and point cloud.'),
    ('camera', 'sensors',
     'Grab camera frames (sheets 3.6, 3.7): RGBD colour + depth with a metre scale, or the CSI 360 views.'),
    ('stop-sign', 'stop_sign',
     'Drive straight, detect the stop sign (HSV red + depth, sheet 5.1) and stop in front of it (5.2).'),
    ('lane-follow', 'lane_follow',
     'Follow the lane with the RGBD camera (HSV yellow line, linear fit, pure pursuit; sheet 5.3).'),
    ('avoid', 'avoid',
     'LIDAR obstacle detection and avoidance (sheet 6.1): stop, steer or both, with collisions checked.'),
    ('grade', 'grade',
     "Grade a submission against lab sheets: block tasks call the student's blocks on given inputs,\nscenario tasks run the lab with the student's blocks and params.yaml. Every task runs in its\nown process with a time, memory and output limit. Exit 0 when every task passes, 1 when one\nfails, 2 for bad input."),
    ('labs', 'grade',
     "List the lab sheets qcarlab grade knows (installed with qcarlab), or one sheet's tasks; with\ncheck, self-check sheets: the untouched template (qcarlab template) must earn 0 points and\nqcarlab's reference blocks every point, so every point depends on the student. Exit 1 when a\nsheet fails its check."),
    ('blocks', 'lab',
     "List a lab's blocks (the sheet's Simulink blocks by name): signature, units, sheet section."),
    ('template', 'lab',
     'Write a student workspace for a lab: one file per block to fill, params.yaml, answers.md.'),
    ('onboard', 'onboard',
     'The car-side server: one Python file that runs on a QCar 1 (Python 3.6) or QCar 2 (3.8) as shipped.'),
    ('deploy', 'onboard',
     'Copy the car-side server to a QCar over ssh/scp, store a token there, print the command that starts it.'),
    ('warm', 'warmstart',
     'Keep lab commands quick to start: a warm server that has loaded qcarlab once forks each one.'),
    ('replay', 'replay',
     'Recordings: what they hold (replay one with --car replay:FILE on a lab command).'),
    ('detect', 'detect',
     "Run the lab's perception on your own photos and videos: lane lines, stop signs."),
)
