"""Registry and progress: named job stages with an ETA, validation losses per
version, and a model's highest version number ever handed out.

- jobs.stage ("observer", "epoch 12/150", "knode-mhe on flight3 (2/4)"), jobs.eta_s (seconds left as
  estimated when written) and jobs.progress_at (when it was written: the ETA read later counts down from it).
- model_versions.validation_losses: the validation loss per epoch next to ``losses`` (None before 0006).
- registered_models.last_version: version numbers are never handed out twice, also after a version is
  deleted (set to each model's highest version here).

Revision ID: 0006_registry
Revises: 0005
Create Date: 2026-11-24
"""
import sqlalchemy as sa
from alembic import op

revision = "0006_registry"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("jobs", sa.Column("stage", sa.String(length=200), nullable=True))
    op.add_column("jobs", sa.Column("eta_s", sa.Float(), nullable=True))
    op.add_column("jobs", sa.Column("progress_at", sa.DateTime(), nullable=True))
    op.add_column("model_versions", sa.Column("validation_losses", sa.JSON(), nullable=True))
    op.add_column("registered_models", sa.Column("last_version", sa.Integer(), nullable=False, server_default="0"))
    op.execute("UPDATE registered_models SET last_version = COALESCE((SELECT MAX(version) FROM model_versions "
               "WHERE model_versions.name = registered_models.name), 0)")


def downgrade() -> None:
    with op.batch_alter_table("registered_models") as batch:
        batch.drop_column("last_version")
    with op.batch_alter_table("model_versions") as batch:
        batch.drop_column("validation_losses")
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("progress_at")
        batch.drop_column("eta_s")
        batch.drop_column("stage")
