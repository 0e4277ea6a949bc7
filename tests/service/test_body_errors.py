"""A body that is not JSON is the body's 422 (never a field "0", the parser's offset), and the
API's own description names the reference it calibrates against."""

from __future__ import annotations

import pytest
from test_service import assert_problem

pytestmark = pytest.mark.redis


@pytest.mark.parametrize(
    ("body", "why"),
    [(b"not json {", "Expecting value at character 0"), (b'{"name": "x",', "at character 13")],
)
def test_a_body_that_is_not_json_names_the_body(api, body, why):
    problem = assert_problem(
        api.post("/v1/calibrations", content=body, headers={"content-type": "application/json"}),
        422,
    )
    assert [e["field"] for e in problem["errors"]] == ["body"]
    message = problem["errors"][0]["message"]
    assert message.startswith("the body is not valid JSON") and why in message
    assert "character" in message and problem["detail"].startswith("body: ")


def test_the_description_names_the_fem_reference_of_either_kind(api):
    description = api.get("/openapi.json").json()["info"]["description"]
    assert "finite element" in description and "tetrahedra" in description
    assert "hexahedral FEM reference" not in description
