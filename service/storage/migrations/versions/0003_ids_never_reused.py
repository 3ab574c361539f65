"""ids are never reused: SQLite tables whose ids are referenced get AUTOINCREMENT.

Without it SQLite hands out max(id) + 1, so after a delete the next upload took the deleted flight's id:
lineage pointed at the wrong flight and a retried DELETE removed a different one.  Each table is rebuilt
with its rows (foreign keys are off during migrations, see Database.migrate); SQLite's sequence starts at
the largest id kept.  PostgreSQL sequences never go back: nothing to do there.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22
"""
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

TABLES = ("flights", "model_versions", "jobs", "evaluations", "diagnoses", "results")


def upgrade() -> None:
    if op.get_bind().dialect.name != "sqlite":
        return
    for table in TABLES:
        with op.batch_alter_table(table, recreate="always", table_kwargs={"sqlite_autoincrement": True}):
            pass


def downgrade() -> None:
    if op.get_bind().dialect.name != "sqlite":
        return
    for table in TABLES:
        with op.batch_alter_table(table, recreate="always"):
            pass
