"""The `colony` command line: one entry point for every process role and lab script.

httpx imports its own command line (click, pygments, rich.syntax) when they are installed;
nothing here uses it and it would cost every `colony` call ~20 ms, so it is marked absent
(None in sys.modules: httpx then skips it) before httpx loads.
"""

import sys

sys.modules.setdefault("httpx._main", None)  # type: ignore[arg-type]  # None means "absent"
