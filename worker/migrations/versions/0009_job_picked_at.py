"""jobs.picked_at: when a worker's fair pick last gave the job a worker (issue 42).

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-29

Workers took the queue in the order it was sent, so one tenant's queued jobs went before
another's newer one however many workers the first already held. A free worker now asks the
job store whose turn it is (`worker.fair`): the tenant with the fewest jobs on a worker, then
the one served longest ago. `picked_at` says when a job was given a worker: a job picked and not
yet claimed holds that worker (its process is starting), and a tenant's latest pick is when it
was last served. Existing rows have none (never picked).
"""

from alembic import op
import sqlalchemy as sa
import worker.models


revision = '0009'
down_revision = '0008'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('picked_at', worker.models.UTCDateTime(timezone=True),
                                      nullable=True))
        batch_op.create_index('ix_jobs_tenant_picked', ['tenant', 'picked_at'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_index('ix_jobs_tenant_picked')
        batch_op.drop_column('picked_at')
