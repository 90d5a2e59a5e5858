"""Container health check: exit 0 when the service answers GET /ready with 200, 1 otherwise.

Standard library only, so it runs with any Python in the image. The port follows IFNET_PORT;
IFNET_HEALTHCHECK_URL overrides the whole URL.
"""

import os
import sys
import urllib.error
import urllib.request
from collections.abc import Mapping

READY_PATH = "/ready"  # 200 once the model is loaded and warmed up, 503 before and while stopping


def health_url(env: Mapping[str, str] = os.environ) -> str:
    return env.get("IFNET_HEALTHCHECK_URL") or f"http://127.0.0.1:{env.get('IFNET_PORT', '8000')}{READY_PATH}"


def main() -> int:
    url = health_url()
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # never via an HTTP proxy
    try:
        with opener.open(url, timeout=4) as response:
            status = response.status
    except urllib.error.HTTPError as error:
        status = error.code
    except (OSError, ValueError) as error:
        print(f"unhealthy: {url}: {error}")
        return 1
    if status != 200:
        print(f"unhealthy: {url} answered {status}")
        return 1
    print(f"healthy: {url} answered 200")
    return 0


if __name__ == "__main__":
    sys.exit(main())
