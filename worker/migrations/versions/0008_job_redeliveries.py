"""jobs.redeliveries: the redelivery cap's count, apart from the attempt number (issue 42).

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-29

`attempts` was both the number of a job's latest run and the redelivery cap's count, so a retry
(which resets the count) and a worker shutting down (which gives its claim back) made the next
run reuse an attempt number: a part's runs read (1, cancelled) then (1, succeeded). The count
moves to `redeliveries`; `attempts` only goes up. Existing rows keep their count.
"""

from alembic import op
import sqlalchemy as sa


revision = '0008'
down_revision = '0007'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column('jobs', sa.Column('redeliveries', sa.Integer(), server_default='0',
                                    nullable=False))
    op.execute("UPDATE jobs SET redeliveries = attempts")


def downgrade() -> None:
    op.drop_column('jobs', 'redeliveries')
