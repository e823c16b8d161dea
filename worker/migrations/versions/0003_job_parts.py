"""jobs.parent_id, part_index, part_frames: a sequence job's parts (docs/design.md 4.4).

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-26

A part is a row of `jobs` (so it has the lease, heartbeat, attempts, dispatch and cancel of any
job) whose parent_id names the sequence job it belongs to. A plain indexed column, not a foreign
key, for the reason migration 0002 gives (SQLite adds a foreign key to an existing table only by
rebuilding it); the job store deletes a parent's parts with it.
"""

from alembic import op
import sqlalchemy as sa


revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column('jobs', sa.Column('parent_id', sa.String(length=32), nullable=True))
    op.add_column('jobs', sa.Column('part_index', sa.Integer(), nullable=True))
    op.add_column('jobs', sa.Column('part_frames', sa.JSON(), nullable=True))
    op.add_column('jobs', sa.Column('parts', sa.Integer(), nullable=False,
                                    server_default='0'))
    op.create_index(op.f('ix_jobs_parent_id'), 'jobs', ['parent_id'], unique=False)


def downgrade() -> None:
    op.drop_index(op.f('ix_jobs_parent_id'), table_name='jobs')
    op.drop_column('jobs', 'parts')
    op.drop_column('jobs', 'part_frames')
    op.drop_column('jobs', 'part_index')
    op.drop_column('jobs', 'parent_id')
