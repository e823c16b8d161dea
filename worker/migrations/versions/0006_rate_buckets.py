"""rate_buckets: the token buckets of the API's per-tenant rate limits (issue 42).

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-29

Every API process shares the job store, so a limit kept there holds across processes (several
`dgs serve --no-worker` behind a load balancer) on SQLite and PostgreSQL alike. A row per
tenant and limit: the tokens left and when they were counted (seconds since the epoch).
"""

from alembic import op
import sqlalchemy as sa


revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'rate_buckets',
        sa.Column('key', sa.String(length=128), nullable=False),
        sa.Column('tokens', sa.Float(), nullable=False),
        sa.Column('stamp', sa.Float(), nullable=False),
        sa.PrimaryKeyConstraint('key', name=op.f('pk_rate_buckets')),
    )


def downgrade() -> None:
    op.drop_table('rate_buckets')
