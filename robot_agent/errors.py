"""Exceptions of the robot agent.

Hierarchy:
    AgentError               root; catch this to handle any failure of `robot_agent`
    └── SerialLinkError      the BasicX link failed
        ├── FrameError       one line is not a valid frame (the decoder returns it, never raises it)
        ├── LinkDeadError    no valid reply after every retry: cable, power or firmware gone
        └── FirmwareError    the firmware answered, but refused the request (ERR CMD / ERR ARG)

Bad arguments to functions raise plain `ValueError`.
"""


class AgentError(Exception):
    """Root of every error raised by `robot_agent`."""


class SerialLinkError(AgentError):
    """The serial link to the BasicX micro-controller failed."""


class LinkDeadError(SerialLinkError):
    """No valid reply within the retry budget; the motors are then under the firmware watchdog."""


class FirmwareError(SerialLinkError):
    """The firmware refused a well-formed request; retrying would not help."""
