"""The car over the network: the qcarlab protocol (``protocol``), the server that exposes any Car
(``server``), sensor frame types shared by both ends (``frames``) and test helpers (``testing``).
The client is :class:`qcarlab.car.tcp.TcpCar`; the wire format is documented in docs/protocol.md.
"""
