"""What crosses a process boundary: pydantic models of configs and wire messages.

Depends on pydantic (and numpy for array codecs) only, so every process role can import it.
"""
