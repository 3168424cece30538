"""Programs that run on the robot besides the endpoint (``fetchsync.protocol``).

Each is sent as source and run by the robot's Python 3.6+; standard library only.
``reaper`` (a command that ends with its channel), ``account_robot``
(create-account's root part).
"""
