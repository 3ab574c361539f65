"""/openapi.json documents the reports every GET serves: the 200 response of the evaluation, diagnosis and
model routes has a schema naming the fields users read, resolved through its $refs."""
from utils.service import flight_csv, running_app, train, upload

ROUTES = {
    "/evaluations/{evaluation_id}": {"headline", "flights", "learned", "flights_scored"},
    "/diagnoses/{diagnosis_id}": {"effects", "thrust_source", "vehicle_fits_prior", "repair", "fitting_flights",
                                  "scored_flights", "before", "after", "registered"},
    "/models": {"items", "total"},
    "/models/{name}": {"versions", "aliases", "latest_version"},
    "/models/{name}/versions/{version}": {"training_flights", "validation_flights", "learned", "learned_note",
                                          "prior"},
    "/models/{name}/versions/{version}/lineage": {"training_flights", "learned", "parent", "children",
                                                  "diagnosis"},
    "/models/{name}/versions/{version}/metadata": {"system", "training_flights", "validation_flights", "learned",
                                                   "envelope", "format_version", "prior_params"},
}
# fields of nested schemas: (route, path of properties to follow, fields expected there)
NESTED = [
    ("/evaluations/{evaluation_id}", ("flights",), {"yardsticks", "flight", "excluded"}),
    # every scored flight counted once: better beyond, worse beyond, within its interval, or undecided
    ("/evaluations/{evaluation_id}", ("headline",), {"flights_better_beyond_interval", "flights_worse_beyond_interval",
                                                     "flights_within_interval", "flights_undecided",
                                                     "flights_undecided_names", "flights_scored"}),
    ("/diagnoses/{diagnosis_id}", ("effects",), {"params", "units", "ci95", "identified", "at_bound"}),
    ("/diagnoses/{diagnosis_id}", ("repair",), {"improves", "reason"}),
]


def resolve(spec: dict, schema: dict) -> dict:
    """Follow $ref, arrays, and `anyOf` with null down to an object schema."""
    while True:
        if "$ref" in schema:
            schema = spec["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
        elif schema.get("type") == "array":
            schema = schema["items"]
        elif "anyOf" in schema:
            schema = next(s for s in schema["anyOf"] if s.get("type") != "null")
        else:
            return schema


def ok_schema(spec: dict, route: str) -> dict:
    content = spec["paths"][route]["get"]["responses"]["200"]["content"]["application/json"]
    return resolve(spec, content["schema"])


def test_report_routes_document_their_200_schema(tmp_path):
    with running_app(tmp_path / "home") as client:
        spec = client.get("/openapi.json").json()
    for route, keys in ROUTES.items():
        properties = ok_schema(spec, route).get("properties", {})
        assert keys <= set(properties), (route, keys - set(properties))
    for route, path, keys in NESTED:
        schema = ok_schema(spec, route)
        for name in path:
            schema = resolve(spec, schema["properties"][name])
        assert keys <= set(schema["properties"]), (route, path, keys - set(schema["properties"]))
    # the typed fields carry their units and meaning into /docs
    effect = resolve(spec, ok_schema(spec, "/diagnoses/{diagnosis_id}")["properties"]["effects"])
    assert "interval" in effect["properties"]["ci95"]["description"]


def test_a_bad_horizon_is_a_422_naming_the_valid_range(tmp_path):
    with running_app(tmp_path / "home") as client:
        for horizon in (0, 501, "twenty"):
            answer = client.post("/evaluations", json={"model": "m:1", "flights": [1], "horizon": horizon})
            assert answer.status_code == 422, answer.text
            assert "horizon" in answer.json()["detail"]
        assert "greater than or equal to 1" in client.post("/evaluations", json={
            "model": "m:1", "flights": [1], "horizon": 0}).json()["detail"]
        assert "less than or equal to 500" in client.post("/evaluations", json={
            "model": "m:1", "flights": [1], "horizon": 501}).json()["detail"]


def test_a_versions_metadata_is_its_model_files_meta_and_prior(tmp_path):
    with running_app(tmp_path / "home") as client:
        flight_id = upload(client, flight_csv(tmp_path, 0)).json()["id"]
        train(client, "quad", flight_id)
        version = client.get("/models/quad/versions/1").json()
        meta = client.get("/models/quad/versions/1/metadata")
        assert meta.status_code == 200, meta.text
        body = meta.json()
        assert body["prior_params"] == version["prior"]["prior_params"]
        assert [f["name"] for f in body["training_flights"]] == [version["training_flight"]["name"]]
        assert body["training_flights"][0]["sha256"] and body["validation_flights"] == []
        assert body["learned"] == version["learned"] and set(body["envelope"])
        assert client.get("/models/quad/versions/9/metadata").status_code == 404
