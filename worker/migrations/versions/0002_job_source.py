"""jobs.source_job_id: the reconstruction a relight job renders.

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-06

A plain indexed column, not a foreign key: SQLite adds a foreign key to an existing table only
by rebuilding it (Alembic's batch mode), and with foreign keys on (worker.db switches them on)
dropping the old `jobs` table would cascade to every job's events, logs and artifacts. The job
store keeps the reference honest instead (JobStore.create_render locks the source; deleting a
job is refused while an active job needs it and clears the field of finished ones).
"""

from alembic import op
import sqlalchemy as sa


revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column('jobs', sa.Column('source_job_id', sa.String(length=32), nullable=True))
    op.create_index(op.f('ix_jobs_source_job_id'), 'jobs', ['source_job_id'], unique=False)


def downgrade() -> None:
    op.drop_index(op.f('ix_jobs_source_job_id'), table_name='jobs')
    op.drop_column('jobs', 'source_job_id')  # in place on SQLite >= 3.35, no table rebuild
