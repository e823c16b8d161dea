"""idempotency_keys: a submit's Idempotency-Key and the job it made (issue 32).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-27

Unique per (tenant, key): a key row is inserted in the transaction that adds its job, so of two
submits racing with one key exactly one commits and the other finds the first's job. A foreign
key with ON DELETE CASCADE (a new table, so SQLite needs no rebuild): a key goes with its job.
"""

from alembic import op
import sqlalchemy as sa
import worker.models


revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'idempotency_keys',
        sa.Column('id', sa.BigInteger().with_variant(sa.Integer(), 'sqlite'),
                  autoincrement=True, nullable=False),
        sa.Column('tenant', sa.String(length=64), nullable=False),
        sa.Column('key', sa.String(length=255), nullable=False),
        sa.Column('request_sha256', sa.String(length=64), nullable=False),
        sa.Column('job_id', sa.String(length=32), nullable=False),
        sa.Column('created_at', worker.models.UTCDateTime(timezone=True),
                  nullable=False),
        sa.Column('expires_at', worker.models.UTCDateTime(timezone=True),
                  nullable=False),
        sa.ForeignKeyConstraint(['job_id'], ['jobs.id'],
                                name=op.f('fk_idempotency_keys_job_id_jobs'),
                                ondelete='CASCADE'),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_idempotency_keys')),
        sa.UniqueConstraint('tenant', 'key', name='uq_idempotency_keys_tenant_key'),
    )
    op.create_index(op.f('ix_idempotency_keys_job_id'), 'idempotency_keys', ['job_id'],
                    unique=False)
    op.create_index(op.f('ix_idempotency_keys_expires_at'), 'idempotency_keys',
                    ['expires_at'], unique=False)


def downgrade() -> None:
    op.drop_index(op.f('ix_idempotency_keys_expires_at'), table_name='idempotency_keys')
    op.drop_index(op.f('ix_idempotency_keys_job_id'), table_name='idempotency_keys')
    op.drop_table('idempotency_keys')
