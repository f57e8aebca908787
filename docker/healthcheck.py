"""Container health probe: exit 0 when this container's server answers 200 on a path.

    python /opt/stylestream/healthcheck.py            # /healthz: the process is alive (HEALTHCHECK)
    python /opt/stylestream/healthcheck.py /readyz    # models loaded and not draining (compose)

A file rather than an inline `python -c` so the port follows STYLESTREAM_PORT like the server does,
and so the image needs no curl."""

from __future__ import annotations

import os
import sys
import urllib.request


def main(argv: list[str]) -> int:
    path = argv[0] if argv else "/healthz"
    url = f"http://127.0.0.1:{os.environ.get('STYLESTREAM_PORT', '8000')}{path}"
    try:
        with urllib.request.urlopen(url, timeout=2) as response:
            return 0 if response.status == 200 else 1
    except OSError as error:  # URLError and HTTPError (503 while loading or draining) are OSErrors
        print(f"{url}: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
