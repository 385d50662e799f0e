"""Schemathesis against the app's OpenAPI schema, fixed seed, small budget: no request it generates gets
a 5xx, every status code it gets is declared for its route, and every response matches its schema.

The suite runs 8 examples per operation (about 40 s on 2 cores: the whole suite has 8 minutes);
``STAGE_FUZZ_EXAMPLES=200 pytest tests/api/test_fuzz.py`` runs the long campaign (minutes)."""

from __future__ import annotations

import os

import pytest
import schemathesis
from hypothesis import HealthCheck, seed, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from schemathesis.checks import not_a_server_error, response_schema_conformance, status_code_conformance  # noqa: E402

from api.app import create_app  # noqa: E402
from tests.api.conftest import AUTH, make_settings  # noqa: E402
from tests.api.fakework import make_take_file  # noqa: E402
from tests.api.pattern_rig import RIG, PatternCamera  # noqa: E402

pytestmark = pytest.mark.slow

# raw take uploads: random bytes, or something that starts like HDF5
schemathesis.openapi.media_type(
    "application/x-hdf5", st.binary(max_size=512) | st.binary(max_size=256).map(lambda b: b"\x89HDF\r\n\x1a\n" + b)
)


@pytest.fixture(scope="module")
def api_app(tmp_path_factory):
    data = tmp_path_factory.mktemp("fuzz") / "data"
    (data / "takes").mkdir(parents=True)
    make_take_file(data / "takes" / "take1.h5", 2, masks=True)
    (data / "rig.toml").write_text(RIG)
    app = create_app(make_settings(data, max_upload_bytes=1 << 16), work="tests.api.fakework:process_take",
                     driver_factory=PatternCamera, start_runner=False)
    yield app
    cap = app.state.capture
    if cap.busy:
        cap.stop()
        cap.wait(30)


@pytest.fixture(scope="module")
def api_schema(api_app):
    return schemathesis.openapi.from_asgi("/openapi.json", api_app)


schema = schemathesis.pytest.from_fixture("api_schema")


#: cases run, by outcome (printed at the end of the module with -s; figures in the closing notes)
TALLY = {"cases": 0, "5xx": 0}


@pytest.fixture(scope="module", autouse=True)
def _tally():
    yield
    print(f"\nschemathesis: {TALLY['cases']} cases, {TALLY['5xx']} server errors")


#: examples per operation (the suite's budget; raise it for a long campaign)
EXAMPLES = int(os.environ.get("STAGE_FUZZ_EXAMPLES", "8"))


@schema.parametrize()
@seed(15)
@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True, database=None)
def test_no_server_errors(case):
    response = case.call(headers=AUTH)
    TALLY["cases"] += 1
    TALLY["5xx"] += response.status_code >= 500
    assert response.status_code < 500, (case.method, case.formatted_path, response.status_code, response.text[:300])
    case.validate_response(response, checks=[not_a_server_error, response_schema_conformance, status_code_conformance])
    if response.status_code >= 400:
        ctype = response.headers.get("content-type") or ""
        ctype = ctype[0] if isinstance(ctype, list) else ctype
        assert ctype.startswith("application/json"), ctype
        assert "Traceback" not in response.text


def test_the_schema_says_which_routes_need_the_token(api_app, tmp_path):
    """Reads are open unless ``read_protected`` (the schema lists "no token" beside the bearer
    token); writes need the token; both as the service answers."""
    from fastapi.testclient import TestClient

    paths = api_app.openapi()["paths"]
    assert paths["/takes"]["get"]["security"] == [{}, {"HTTPBearer": []}]
    assert paths["/takes/{take_id}"]["delete"]["security"] == [{"HTTPBearer": []}]
    assert {"401", "403", "400", "404"} <= set(paths["/takes/{take_id}"]["delete"]["responses"])
    with TestClient(api_app) as c:
        assert c.get("/takes").status_code == 200
        assert c.delete("/takes/nope").status_code == 401
    data = tmp_path / "data"
    protected = create_app(make_settings(data, read_protected=True), start_runner=False)
    assert protected.openapi()["paths"]["/takes"]["get"]["security"] == [{"HTTPBearer": []}]
    with TestClient(protected) as c:
        assert c.get("/takes").status_code == 401
