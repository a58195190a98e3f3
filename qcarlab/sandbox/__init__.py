"""The student's code in a process of its own, confined: the other half of a graded task.

A graded task is qcarlab's trusted process (:mod:`qcarlab.grading.child`: the simulator, the lab's
diagram, the referee, the results) and the student's process, which loads their files and calls
their blocks when asked; nothing crosses but a block's arguments and its value.

- :mod:`.client`: the trusted side: start the student's process, load files there as remote blocks.
- :mod:`.host`: the student's process: load, call, reply.
- :mod:`.codec`: what crosses: the student's replies as plain values (never a pickle).
- :mod:`.jail`: Linux confinement: namespaces, a read-only view, another user, rlimits.
- :mod:`.cgroup`: one memory limit (and a process cap) for everything the student's process starts.
"""
