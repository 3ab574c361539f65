"""Who may do what, and who did it: API tokens, web sessions, the audit log, and the token name that created
each flight, model version, evaluation and diagnosis.

- api_tokens: one row per token made (the SHA-256 of the token, never the token); a name is unique among the
  tokens not revoked.
- web_sessions: the web sign-ins (hashes of the session id and of the token signed in with).
- audit_log: deletions and token changes; no foreign keys, so deleting rows never removes an entry.
- flights / model_versions / evaluations / diagnoses.created_by: NULL for rows made before, or without a token.

Revision ID: 0008_access
Revises: 0007_training_flights
Create Date: 2026-11-29
"""
import sqlalchemy as sa
from alembic import op

revision = "0008_access"
down_revision = "0007_training_flights"
branch_labels = None
depends_on = None

CREATED_BY = ("flights", "model_versions", "evaluations", "diagnoses")
ACTIVE = sa.text("revoked_at IS NULL")


def upgrade() -> None:
    op.create_table(
        "api_tokens",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=True),
        sa.Column("name", sa.String(64), nullable=False),
        sa.Column("scope", sa.String(10), nullable=False),
        sa.Column("token_hash", sa.String(64), nullable=False, unique=True),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("created_by", sa.String(100), nullable=True),
        sa.Column("revoked_at", sa.DateTime(), nullable=True),
        sa.Column("revoked_by", sa.String(100), nullable=True),
        sqlite_autoincrement=True,
    )
    op.create_index("uq_api_tokens_active_name", "api_tokens", ["name"], unique=True, sqlite_where=ACTIVE,
                    postgresql_where=ACTIVE)
    op.create_table(
        "web_sessions",
        sa.Column("id_hash", sa.String(64), primary_key=True),
        sa.Column("token_hash", sa.String(64), nullable=False),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("expires_at", sa.DateTime(), nullable=False),
    )
    op.create_index("ix_web_sessions_token_hash", "web_sessions", ["token_hash"])
    op.create_index("ix_web_sessions_expires_at", "web_sessions", ["expires_at"])
    op.create_table(
        "audit_log",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=True),
        sa.Column("at", sa.DateTime(), nullable=False),
        sa.Column("actor", sa.String(100), nullable=False),
        sa.Column("action", sa.String(40), nullable=False),
        sa.Column("target", sa.String(300), nullable=False),
        sa.Column("detail", sa.JSON(), nullable=True),
        sqlite_autoincrement=True,
    )
    op.create_index("ix_audit_log_at", "audit_log", ["at"])
    for table in CREATED_BY:
        op.add_column(table, sa.Column("created_by", sa.String(100), nullable=True))


def downgrade() -> None:
    for table in CREATED_BY:
        with op.batch_alter_table(table) as batch:
            batch.drop_column("created_by")
    op.drop_table("audit_log")
    op.drop_table("web_sessions")
    op.drop_index("uq_api_tokens_active_name", table_name="api_tokens")
    op.drop_table("api_tokens")
