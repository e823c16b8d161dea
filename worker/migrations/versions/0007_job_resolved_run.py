"""jobs.resolved_run: the run a reconstruction resolved to at submit (issue 40).

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-29

A job's configuration was resolved twice, at submit (to check it) and again by the worker from
the stored parameters, so a preset changed between submit and a retry changed the job (and the
resume then refused its own run directory). The API now resolves the run once against the
capture (`core.config.ResolvedRun`: preset, frames, configuration, views) and stores it here;
the worker runs it as stored. Null for relight and export jobs, and for jobs stored before this
column, which the worker resolves from their parameters once, as it always did.
"""

from alembic import op
import sqlalchemy as sa


revision = '0007'
down_revision = '0006'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column('jobs', sa.Column('resolved_run', sa.JSON(), nullable=True))


def downgrade() -> None:
    op.drop_column('jobs', 'resolved_run')
