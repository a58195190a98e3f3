"""The car over the network: the server that exposes any Car (``server``), its guards and sensor
pacing, and test helpers (``testing``). The wire format both ends speak lives below ``car/`` and
``net/`` in :mod:`qcarlab.wire`; the client is :class:`qcarlab.car.tcp.TcpCar`; docs/protocol.md
documents it.
"""
