"""results.estimates_blob: the per-step state estimates of a flight's result (FlightEstimates.to_bytes).

Results stored before this have none; an evaluation computes such a flight again instead of answering
from the cache, so every evaluation can export its estimates.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-22
"""
import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("results", sa.Column("estimates_blob", sa.String(length=64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("results") as batch:
        batch.drop_column("estimates_blob")
