"""The upload + model + evaluation flow once against PostgreSQL (LEARNEST_DATABASE_URL), on a throwaway
server started here — skipped when initdb/pg_ctl or the psycopg driver are not installed."""
import pytest
from utils.service import evaluate, flight_csv, running_app, train, upload

pytestmark = pytest.mark.postgres


def test_upload_train_evaluate_on_postgresql(tmp_path, data_dir, postgres_url):
    with running_app(tmp_path / "home", database_url=postgres_url) as client:
        assert client.get("/health").json()["database"] == "postgresql"
        first = upload(client, flight_csv(data_dir, 0))
        assert first.status_code == 201, first.text
        assert upload(client, flight_csv(data_dir, 0), names=["copy.csv"]).status_code == 200
        other = upload(client, flight_csv(data_dir, 1)).json()
        assert client.post("/flights", files=[("files", ("x.bin", b"\x00junk"))]).status_code == 422
        assert client.get("/flights").json()["total"] == 2

        assert train(client, "pgquad", first.json()["id"])["version"] == 1
        assert client.put("/models/pgquad/aliases/production", json={"version": 1}).status_code == 200
        accepted, report = evaluate(client, "pgquad@production", "all-other")
        assert report["model"] == "pgquad:1" and [f["flight"] for f in report["flights"]] == [other["name"]]
        assert report["flights"][0]["excluded"] is False and report["median"]
        again = client.post("/evaluations", json={"model": "pgquad:1", "flights": [other["id"]],
                                                  "methods": ["ukf", "knode-ukf"]}).json()
        assert again["state"] == "succeeded"                        # from the results cache
        assert client.get("/models/pgquad/versions/9").status_code == 404
