"""A model version trained on several flights: every training flight and every validation flight.

- model_versions.training_flights: [{"id", "name", "sha256"}] of every flight the version was trained on, in
  order (the first is also ``training_flight_*``, kept for the readers of a single flight).
- model_versions.validation_flights: the same for the flights held out whole to choose the kept epoch (empty
  for one flight, whose validation is time blocks of that flight).

Existing versions get their one training flight as the list and no validation flights.

Revision ID: 0007_training_flights
Revises: 0006_registry
Create Date: 2026-11-27
"""
import sqlalchemy as sa
from alembic import op

revision = "0007_training_flights"
down_revision = "0006_registry"
branch_labels = None
depends_on = None

versions = sa.table("model_versions", sa.column("id", sa.Integer), sa.column("training_flight_id", sa.Integer),
                    sa.column("training_flight_name", sa.String), sa.column("training_flight_sha256", sa.String),
                    sa.column("training_flights", sa.JSON), sa.column("validation_flights", sa.JSON))


def upgrade() -> None:
    op.add_column("model_versions", sa.Column("training_flights", sa.JSON(), nullable=True))
    op.add_column("model_versions", sa.Column("validation_flights", sa.JSON(), nullable=True))
    bind = op.get_bind()
    rows = bind.execute(sa.select(versions.c.id, versions.c.training_flight_id, versions.c.training_flight_name,
                                  versions.c.training_flight_sha256)).all()
    for row in rows:
        flights = [{"id": row.training_flight_id, "name": row.training_flight_name,
                    "sha256": row.training_flight_sha256}] if row.training_flight_name is not None else []
        bind.execute(versions.update().where(versions.c.id == row.id)
                     .values(training_flights=flights, validation_flights=[]))


def downgrade() -> None:
    with op.batch_alter_table("model_versions") as batch:
        batch.drop_column("validation_flights")
        batch.drop_column("training_flights")
