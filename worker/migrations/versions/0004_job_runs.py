"""jobs.worker, jobs.runs: who ran a job (and each attempt), kept after it ends.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-27

The API showed a part's worker from its lease, which is cleared when the part ends, so a
finished part named no worker and nobody could tell which machine ran which group of pictures
(a bad or slow GPU node) after the fact. `worker` is the last claimant's host/pid; `runs` lists
each claim with its outcome (docs/design.md 4.4).
"""

from alembic import op
import sqlalchemy as sa


revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column('jobs', sa.Column('worker', sa.String(length=256), nullable=True))
    op.add_column('jobs', sa.Column('runs', sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column('jobs', 'runs')
    op.drop_column('jobs', 'worker')
