"""Initial schema: jobs and tokens, exactly as ``Base.metadata.create_all`` made them before
migrations (databases from then are stamped at this revision, see ``jobstore.migrate``).

Revision ID: 0001
Revises:
Create Date: 2026-11-25
"""

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "nepf_jobs",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("owner", sa.String(length=128), nullable=False),
        sa.Column("name", sa.String(length=256), nullable=True),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("config", sa.JSON(), nullable=False),
        sa.Column("dataset", sa.JSON(), nullable=False),
        sa.Column("queue", sa.String(length=32), nullable=False),
        sa.Column("idempotency_key", sa.String(length=256), nullable=True),
        sa.Column("request_hash", sa.String(length=64), nullable=True),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("started_at", sa.DateTime(), nullable=True),
        sa.Column("finished_at", sa.DateTime(), nullable=True),
        sa.Column("enqueued_at", sa.DateTime(), nullable=True),
        sa.Column("enqueue_count", sa.Integer(), nullable=False),
        sa.Column("step", sa.Integer(), nullable=False),
        sa.Column("total", sa.Integer(), nullable=True),
        sa.Column("fraction", sa.Float(), nullable=False),
        sa.Column("stage", sa.String(length=64), nullable=True),
        sa.Column("eta_s", sa.Float(), nullable=True),
        sa.Column("wall_s", sa.Float(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("decisions", sa.JSON(), nullable=True),
        sa.Column("result", sa.JSON(), nullable=True),
        sa.Column("cancel_requested", sa.Boolean(), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("attempt_log", sa.JSON(), nullable=False),
        sa.Column("lease_owner", sa.String(length=128), nullable=True),
        sa.Column("lease_expires", sa.DateTime(), nullable=True),
        sa.Column("completions", sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("owner", "idempotency_key", name="uq_job_owner_idem"),
    )
    op.create_index("ix_nepf_jobs_created_at", "nepf_jobs", ["created_at"], unique=False)
    op.create_index("ix_nepf_jobs_owner", "nepf_jobs", ["owner"], unique=False)
    op.create_index("ix_nepf_jobs_status", "nepf_jobs", ["status"], unique=False)

    op.create_table(
        "nepf_tokens",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("owner", sa.String(length=128), nullable=False),
        sa.Column("name", sa.String(length=128), nullable=False),
        sa.Column("token_hash", sa.String(length=64), nullable=False),
        sa.Column("prefix", sa.String(length=16), nullable=False),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("revoked", sa.Boolean(), nullable=False),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_nepf_tokens_owner", "nepf_tokens", ["owner"], unique=False)
    op.create_index("ix_nepf_tokens_token_hash", "nepf_tokens", ["token_hash"], unique=True)


def downgrade() -> None:
    op.drop_index("ix_nepf_tokens_token_hash", table_name="nepf_tokens")
    op.drop_index("ix_nepf_tokens_owner", table_name="nepf_tokens")
    op.drop_table("nepf_tokens")
    op.drop_index("ix_nepf_jobs_status", table_name="nepf_jobs")
    op.drop_index("ix_nepf_jobs_owner", table_name="nepf_jobs")
    op.drop_index("ix_nepf_jobs_created_at", table_name="nepf_jobs")
    op.drop_table("nepf_jobs")
