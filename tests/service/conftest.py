import os
import uuid

import pytest

from service.store import open_store

#: CI sets this (see .ci/run); elsewhere the PostgreSQL half of the store suite is skipped.
POSTGRES_ENV = "BDF_TEST_POSTGRES_URL"


@pytest.fixture(params=["sqlite", "postgres"])
def store_url(request, tmp_path):
    """A fresh, empty store of each backend, as a URL (processes open their own)."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'data'}"
        return
    base = os.environ.get(POSTGRES_ENV)
    if not base:
        pytest.skip(f"PostgreSQL tests need {POSTGRES_ENV} (e.g. postgresql://postgres@127.0.0.1:5432/test)")
    import psycopg

    schema = f"bdf_test_{uuid.uuid4().hex[:12]}"
    yield f"{base}?schema={schema}"
    with psycopg.connect(base, autocommit=True) as conn:
        conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")


@pytest.fixture
def store(store_url):
    s = open_store(store_url)
    yield s
    s.close()


@pytest.fixture
def spec(store):
    """The region ``town`` (tests.service.test_store.SPEC), created in ``store``."""
    from bdf.region.spec import RegionSpec
    from tests.service.test_store import SPEC

    spec = RegionSpec.model_validate(SPEC)
    store.create_region(spec)
    return spec
