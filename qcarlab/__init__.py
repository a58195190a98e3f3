"""qcarlab: the QCar self-driving lab in Python: a real car over TCP or a built-in simulator.

    import qcarlab
    with qcarlab.open_car("sim", seed=1) as car:
        car.write(0.1, 0.0)
        car.advance(2.0)
        print(car.read().encoder_counts)
"""

from qcarlab.car import open_car

__version__ = "0.1.0"
__all__ = ["open_car", "__version__"]
