"""Schemathesis against the app's OpenAPI schema, fixed seed, small budget: no request it generates gets
a 5xx, every status code it gets is declared for its route, and every response matches its schema.

The suite runs 4 examples per operation (``STAGE_FUZZ_EXAMPLES`` raises it); CI runs the long
campaign (every operation, round after round, for 150 s) beside the suite: ``python -m
tests.api.fuzzing --seconds 150`` (tests/api/fuzzing.py, ``.ci/run``)."""

from __future__ import annotations

import os

import pytest
import schemathesis
from hypothesis import HealthCheck, seed, settings

from api.app import create_app
from tests.api.conftest import make_settings
from tests.api.fuzzing import check_case, close_app, make_app

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def api_app(tmp_path_factory):
    app = make_app(tmp_path_factory.mktemp("fuzz"))
    yield app
    close_app(app)


@pytest.fixture(scope="module")
def api_schema(api_app):
    return schemathesis.openapi.from_asgi("/openapi.json", api_app)


schema = schemathesis.pytest.from_fixture("api_schema")

#: examples per operation (the suite's budget; CI's campaign runs for minutes beside the suite)
EXAMPLES = int(os.environ.get("STAGE_FUZZ_EXAMPLES", "4"))


@schema.parametrize()
@seed(15)
@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True, database=None)
def test_no_server_errors(case):
    check_case(case)


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
