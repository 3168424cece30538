"""fetchsync: mirror a ROS workspace's ``src/`` to a robot over SSH, live and safely.

The package holds the CLI (``fetchsync.cli``, thin), configuration, the SSH
transport and the robot verbs; ``fetchsync.protocol`` is the wire format and
sync core that also runs on the robot; ``fetchsync.agent`` is the long-running
local agent.
"""

__version__ = "0.1.0"
