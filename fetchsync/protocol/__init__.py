"""Wire format, tree model, delta engine and the robot-side endpoint.

This package runs on the robot as well as on the laptop: it imports only the
standard library (xxhash is used when importable on both ends, agreed in the
handshake) and runs on Python 3.6. Its core is pure: functions over bytes and
trees, no sockets, no paths outside the root it is handed.
"""
