"""jobs.yield_asked_at: when the fair share asked a running job to give its worker up (issue 42).

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-29

The fair pick (0009) orders waiting jobs, but a tenant that took every worker while alone kept
them until its jobs ended. A running job of a tenant holding at least two workers more than a
tenant with a waiting job (or one more, with time slicing) is now asked to stop at its next
step and go back to the queue (`worker.fair`): `yield_asked_at` records the ask, so that one
job is asked at a time and the ask survives in the row until the job's next claim. Existing
rows have none.
"""

from alembic import op
import sqlalchemy as sa
import worker.models


revision = '0010'
down_revision = '0009'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('yield_asked_at', worker.models.UTCDateTime(timezone=True),
                                      nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('yield_asked_at')
