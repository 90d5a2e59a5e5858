"""A small Python client for the service, and the `ifnet-register` command line.

    ifnet-register source.ply target.ply --url http://127.0.0.1:8000 [--refine] [--output aligned.ply]

prints the 4x4 transform that moves the source onto the target, and its fitness.
"""

import argparse
import io
import json
import os
import sys
from pathlib import Path
from typing import Any

import httpx
import numpy as np

DEFAULT_URL = "http://127.0.0.1:8000"


class RegistrationError(Exception):
    """The service answered with an error; `status` is the HTTP code, `detail` its explanation and
    `request_id` the id under which the service logged the request (quote it when reporting a 5xx)."""

    def __init__(self, status: int, detail: str, request_id: str | None = None):
        super().__init__(f"HTTP {status}: {detail}" + (f" (request id {request_id})" if request_id else ""))
        self.status = status
        self.detail = detail
        self.request_id = request_id


def _options(options: dict[str, Any]) -> str:
    """Options as /register's JSON: None leaves the service's default, arrays become lists."""
    chosen = {name: value for name, value in options.items() if value is not None}
    return json.dumps(
        {name: np.asarray(value).tolist() if isinstance(value, np.ndarray) else value for name, value in chosen.items()}
    )


class RegistrationClient:
    """Registers point clouds with a running ifnet-serve instance."""

    def __init__(
        self,
        url: str = DEFAULT_URL,
        api_key: str | None = None,
        timeout_s: float = 120.0,
        transport: httpx.BaseTransport | None = None,
    ):
        headers = {"X-API-Key": api_key} if api_key else {}
        self._http = httpx.Client(base_url=url, headers=headers, timeout=timeout_s, transport=transport)

    def __enter__(self) -> "RegistrationClient":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def register(self, source: np.ndarray, target: np.ndarray, **options: Any) -> dict[str, Any]:
        """Register two [N, 3] arrays; options as in /register (model, init, refine, network_points, sampling, ...).

        The arrays go as one NPZ body: much cheaper to encode and parse than JSON lists.
        """
        archive = io.BytesIO()
        np.savez(archive, source=np.asarray(source, np.float64), target=np.asarray(target, np.float64))
        response = self._http.post(
            "/register",
            content=archive.getvalue(),
            headers={"Content-Type": "application/x-npz"},
            params={"options": _options(options)},
        )
        return self._answer(response)

    def register_files(self, source: str | Path, target: str | Path, **options: Any) -> dict[str, Any]:
        """Register two PLY, PCD or NPY files, uploaded as they are."""
        source, target = Path(source), Path(target)
        files = {
            "source": (source.name, source.read_bytes(), "application/octet-stream"),
            "target": (target.name, target.read_bytes(), "application/octet-stream"),
        }
        data = {"options": _options(options)}
        return self._answer(self._http.post("/register", files=files, data=data))

    def health(self) -> dict[str, Any]:
        return self._answer(self._http.get("/health"))

    def ready(self) -> bool:
        return self._http.get("/ready").status_code == 200

    @staticmethod
    def _answer(response: httpx.Response) -> dict[str, Any]:
        if response.is_success:
            return response.json()
        try:
            detail = response.json().get("detail") or response.text
        except ValueError:
            detail = response.text
        raise RegistrationError(response.status_code, str(detail), response.headers.get("x-request-id"))


def _load_matrix(path: str) -> np.ndarray:
    if path.endswith(".npy"):
        return np.load(path, allow_pickle=False)
    return np.loadtxt(path)


def format_report(result: dict[str, Any]) -> str:
    rows = ["transform (source -> target):"]
    rows += ["  " + " ".join(f"{value: .6f}" for value in row) for row in result["transform"]]
    rows.append(
        f"fitness {result['fitness']:.4f}  inlier_rmse {result['inlier_rmse']:.6g}  "
        f"(threshold {result['fitness_threshold']:.6g})"
    )
    verdict = "verified" if result["verified"] else f"NOT verified: {result['reason']}"
    rows.append(f"{verdict}  (stage {result['stage']})")
    model, timings = result["model"], result["timings_ms"]
    rows.append(f"model {model['name']} {model['version']}  total {timings['total_ms']:.0f} ms")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ifnet-register", description="Register two point clouds with ifnet-serve.")
    parser.add_argument("source", help="cloud to move (PLY, PCD or NPY)")
    parser.add_argument("target", help="cloud to align to (PLY, PCD or NPY)")
    parser.add_argument("--url", default=os.environ.get("IFNET_URL", DEFAULT_URL), help="service URL (env IFNET_URL)")
    parser.add_argument("--api-key", default=os.environ.get("IFNET_API_KEY"), help="API key (env IFNET_API_KEY)")
    parser.add_argument("--init", help="initial 4x4 guess: a .npy file or a text file of 4 rows")
    parser.add_argument("--refine", action="store_true", help="refine with ICP on the full clouds")
    parser.add_argument("--refine-distance", type=float, help="ICP correspondence distance, in the clouds' units")
    parser.add_argument(
        "--network-points",
        "--max-points",
        type=int,
        dest="network_points",
        help="points per cloud given to the network",
    )
    parser.add_argument("--model", help="the served model to use, by name (service default: object)")
    parser.add_argument(
        "--method",
        choices=["auto", "ifnet", "global"],
        help="ifnet: the network; global: a search for any rotation; auto (service default): the network, "
        "then the search if the answer fails the check",
    )
    parser.add_argument(
        "--sampling", choices=["fps", "random"], help="subsampling to the network's point count (service default: fps)"
    )
    parser.add_argument("--seed", type=int, help="seed of random sampling and upsampling (service default: 0)")
    parser.add_argument("--output", help="write the moved source cloud to this PLY file")
    parser.add_argument("--json", action="store_true", help="print the service's whole JSON answer")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the answer")
    args = parser.parse_args(argv)
    if not args.timeout > 0:
        parser.error(f"--timeout must be more than 0 seconds, got {args.timeout:g}")

    refine: bool | dict | None = None
    if args.refine or args.refine_distance is not None:
        refine = {"max_distance": args.refine_distance} if args.refine_distance is not None else True
    try:
        init = _load_matrix(args.init) if args.init else None
    except (OSError, ValueError) as error:
        print(f"ifnet-register: --init {args.init}: not a 4x4 matrix in .npy or text ({error})", file=sys.stderr)
        return 1
    try:
        with RegistrationClient(args.url, args.api_key, args.timeout) as client:
            result = client.register_files(
                args.source,
                args.target,
                init=init,
                refine=refine,
                network_points=args.network_points,
                model=args.model,
                method=args.method,
                sampling=args.sampling,
                seed=args.seed,
            )
    except RegistrationError as error:
        print(f"ifnet-register: the service refused: {error}", file=sys.stderr)
        return 1
    except httpx.TimeoutException:
        print(f"ifnet-register: no answer from {args.url} within {args.timeout:g} s; raise --timeout", file=sys.stderr)
        return 1
    except httpx.TransportError as error:
        print(
            f"ifnet-register: cannot reach the service at {args.url} ({error}); is it running? "
            "Point --url (or IFNET_URL) at it",
            file=sys.stderr,
        )
        return 1
    except (OSError, ValueError, httpx.HTTPError) as error:
        print(f"ifnet-register: {error}", file=sys.stderr)
        return 1

    print(json.dumps(result, indent=2) if args.json else format_report(result))
    if args.output:
        try:
            write_moved_source(args.source, np.asarray(result["transform"]), args.output)
        except OSError as error:
            print(f"ifnet-register: --output {args.output}: {error}", file=sys.stderr)
            return 1
        print(f"moved source written to {args.output}", file=sys.stderr)
    return 0


def write_moved_source(source_path: str, transform: np.ndarray, output: str) -> None:
    from service.formats import read_cloud_file, write_ply

    source = read_cloud_file(source_path)
    write_ply(output, source @ transform[:3, :3].T + transform[:3, 3])


if __name__ == "__main__":
    sys.exit(main())
