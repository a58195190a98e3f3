"""qcarlab's simulated QCar as gymnasium environments (``pip install "qcarlab[gym]"``).

    import gymnasium
    import qcarlab.gym                                    # registers the ids below
    env = gymnasium.make("qcarlab/Hallway-v0")            # or "qcarlab/QCar-v0", world="track"
    envs = gymnasium.make_vec("qcarlab/Track-v0", num_envs=8, vectorization_mode="sync")

Ids: ``qcarlab/QCar-v0`` (any world: ``world=NAME|FILE``, default hallway) and one per shipped
world: ``qcarlab/Hallway-v0``, ``qcarlab/Obstacles-v0``, ``qcarlab/StopSign-v0``,
``qcarlab/Studio-v0``, ``qcarlab/Track-v0``. Without importing this module first,
``gymnasium.make("qcarlab.gym:qcarlab/Hallway-v0")`` imports it. Every keyword of
:class:`~qcarlab.gym.env.QCarEnv` (observations, realism, rate, reward, ...) passes through
``make``. Many cars: gymnasium's ``make_vec`` (sync; each car its own simulator, seeded
``seed``, ``seed + 1``, ...) or :func:`make_vec` here, the same with qcarlab's defaults.
"""

from __future__ import annotations

try:
    import gymnasium
except ImportError as exc:  # an optional extra
    raise ImportError("qcarlab.gym needs gymnasium: pip install \"qcarlab[gym]\"") from exc

from qcarlab.gym.env import OBSERVATIONS, READOUT_FIELDS, QCarEnv, progress_reward

__all__ = ["ENV_IDS", "OBSERVATIONS", "READOUT_FIELDS", "QCarEnv", "make_vec", "progress_reward"]

ENTRY_POINT = "qcarlab.gym.env:QCarEnv"


def _env_id(world: str) -> str:
    """``stop-sign`` -> ``qcarlab/StopSign-v0``."""
    return "qcarlab/" + "".join(part.capitalize() for part in world.replace("_", "-").split("-")) + "-v0"


def _register() -> tuple[str, ...]:
    from qcarlab.sim.world import list_worlds

    ids = ["qcarlab/QCar-v0"]
    if ids[0] not in gymnasium.registry:
        gymnasium.register(ids[0], entry_point=ENTRY_POINT)
    for name, _ in list_worlds():
        env_id = _env_id(name)
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point=ENTRY_POINT, kwargs={"world": name})
        ids.append(env_id)
    return tuple(ids)


ENV_IDS = _register()  #: the registered ids


def make_vec(num_envs: int, world: str = "hallway", **kwargs):
    """``num_envs`` cars in ``world``, each its own simulator, stepped one after the other in this
    process (gymnasium's ``SyncVectorEnv``; same-step autoreset): ``reset(seed=s)`` seeds them
    ``s, s + 1, ...``. ``kwargs`` are :class:`QCarEnv`'s."""
    if not (isinstance(num_envs, int) and num_envs >= 1):
        from qcarlab.errors import InputError

        raise InputError(f"num_envs must be a positive integer, got {num_envs!r}")
    return gymnasium.make_vec("qcarlab/QCar-v0", num_envs=num_envs, vectorization_mode="sync", world=world, **kwargs)
