"""The link to the robot, laptop side: resolve, connect, talk.

``session`` (resolve a target, open its connection and state), ``connection``
(the one connection: requests and deadlines), ``ssh`` (paramiko as ``ssh``
would), ``transport`` (the transport interface and the ``local`` robot),
``mux`` (the connection master that keeps an SSH session warm).
"""
