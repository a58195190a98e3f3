"""A strict fake of Quanser's Python API (quanser.hardware, .devices, .multimedia), for qcarlab's
tests only: see _fake.py. It is not Quanser's code; it refuses what the real cards refuse."""
