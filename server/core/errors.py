"""Exceptions of the server package.

Hierarchy:
    ServerError              root; catch this to handle any failure of `server`
    ├── NotFoundError        no run, generation or controller with that id (HTTP 404)
    ├── InvalidInputError    a value the request names cannot be used, e.g. an ambiguous sha256
    │                        prefix (HTTP 422)
    ├── TransitionError      the run's status does not allow the requested change (HTTP 409)
    └── UnconfirmedError     what was asked for rests on a worker's claim that the server's own
                             evaluation does not repeat, so it is not served (HTTP 409)

Bad arguments raise plain `ValueError`. The app answers a ServerError that reaches a route
with its `status_code` and message; `HTTPException` is raised only in `server/routes`.
"""


class ServerError(Exception):
    """Root of every error raised by `server`; `status_code` is its HTTP answer (app.py maps it)."""

    status_code = 500


class NotFoundError(ServerError):
    """The requested run, generation or controller does not exist."""

    status_code = 404


class InvalidInputError(ServerError):
    """A value in the request is malformed or ambiguous (a sha256 prefix matching several)."""

    status_code = 422


class TransitionError(ServerError):
    """A lifecycle change that the run's current status forbids (e.g. resuming a completed run)."""

    status_code = 409


class UnconfirmedError(ServerError):
    """The controller asked for was chosen by a worker's claimed fitness (or descriptors) that
    the server's own evaluation does not repeat bit for bit: a forgery is never served."""

    status_code = 409


class BusyError(ServerError):
    """The server is rebuilding another request's generation (a simulation): asked again
    soon, it answers (a reader cannot make it simulate on every core at once)."""

    status_code = 503
    retry_after_s = 2
