"""Schemathesis against the app's OpenAPI schema: the app it runs on and the checks of every case,
shared by tests/api/test_fuzz.py (a few examples per operation, in the suite) and the campaign CI
runs beside the suite (``.ci/run``)::

    python -m tests.api.fuzzing --seconds 150

The campaign goes over every operation of the schema, with the token, a few examples each, round
after round with a new seed, until its time is up; it prints a line per failing operation and the
tally, and exits 1 when any case got a server error, a status code its route does not declare or a
response that violates the schema (0 otherwise). It runs on the fake work and the pattern rig, so
capture start is fuzzed too (it records test patterns, never real data).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import schemathesis
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error, response_schema_conformance, status_code_conformance

from api.app import create_app
from tests.api.conftest import AUTH, make_settings
from tests.api.fakework import make_take_file
from tests.api.pattern_rig import RIG, PatternCamera

# raw take uploads: random bytes, or something that starts like HDF5
schemathesis.openapi.media_type(
    "application/x-hdf5", st.binary(max_size=512) | st.binary(max_size=256).map(lambda b: b"\x89HDF\r\n\x1a\n" + b)
)


def make_app(root: Path):
    """The app on a data root holding one take with masks and the pattern rig (fake work, no runner)."""
    data = Path(root) / "data"
    (data / "takes").mkdir(parents=True)
    make_take_file(data / "takes" / "take1.h5", 2, masks=True)
    (data / "rig.toml").write_text(RIG)
    return create_app(make_settings(data, max_upload_bytes=1 << 16), work="tests.api.fakework:process_take",
                      driver_factory=PatternCamera, start_runner=False)


def close_app(app) -> None:
    """Stop a capture the cases left running."""
    cap = app.state.capture
    if cap.busy:
        cap.stop()
        cap.wait(30)


def check_case(case) -> int:
    """Call the case with the token and check its answer; -> the status code. AssertionError (or
    schemathesis' failure) when the answer is a server error, undeclared, off the schema, or an
    error that is not JSON / shows a traceback."""
    response = case.call(headers=AUTH)
    assert response.status_code < 500, (case.method, case.formatted_path, response.status_code, response.text[:300])
    case.validate_response(response, checks=[not_a_server_error, response_schema_conformance, status_code_conformance])
    if response.status_code >= 400:
        ctype = response.headers.get("content-type") or ""
        ctype = ctype[0] if isinstance(ctype, list) else ctype
        assert ctype.startswith("application/json"), ctype
        assert "Traceback" not in response.text
    return response.status_code


def _run_operation(op, examples: int, run_seed: int, tally: dict) -> None:
    @seed(run_seed)
    @settings(max_examples=examples, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    @given(case=op.as_strategy())
    def run(case):
        tally["cases"] += 1
        check_case(case)

    run()


def campaign(seconds: float, *, examples: int = 4, out=sys.stdout) -> dict:
    """Fuzz every operation, round after round (a new seed each), for ``seconds``.

    Returns
    -------
    dict
        ``cases``, ``rounds``, ``seconds``, ``operations`` and ``failures`` (``[(operation, error)]``).
    """
    tally = {"cases": 0, "rounds": 0, "failures": []}
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="fuzz-") as tmp:
        app = make_app(Path(tmp))
        try:
            schema = schemathesis.openapi.from_asgi("/openapi.json", app)
            ops = [r.ok() for r in schema.get_all_operations()]
            failed: set[str] = set()
            while time.monotonic() - t0 < seconds:
                for i, op in enumerate(ops):
                    if time.monotonic() - t0 >= seconds:
                        break
                    if op.label in failed:  # one failure an operation is enough; the rest go on
                        continue
                    try:
                        _run_operation(op, examples, tally["rounds"] * 1000 + i, tally)
                    except Exception as exc:  # noqa: BLE001 - any failure of a case is reported, not raised
                        failed.add(op.label)
                        line = str(exc).strip().splitlines()
                        tally["failures"].append((op.label, line[0] if line else type(exc).__name__))
                        print(f"FAILED {op.label}: {' | '.join(line[:6])}", file=out, flush=True)
                tally["rounds"] += 1
        finally:
            close_app(app)
    tally["seconds"] = round(time.monotonic() - t0, 1)
    tally["operations"] = len(ops)
    return tally


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.api.fuzzing", description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=150.0, help="time budget (default 150)")
    p.add_argument("--examples", type=int, default=4, help="examples per operation and round (default 4)")
    args = p.parse_args(argv)
    if args.seconds <= 0 or args.examples < 1:
        p.error("--seconds must be > 0 and --examples >= 1")
    t = campaign(args.seconds, examples=args.examples)
    print(f"schemathesis campaign: {t['cases']} cases over {t['operations']} operations in {t['rounds']} rounds, "
          f"{t['seconds']} s: {len(t['failures'])} operations failed (server errors, undeclared status codes, "
          "schema violations)", flush=True)
    return 1 if t["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
