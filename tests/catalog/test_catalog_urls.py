"""Catalog URLs (file://, the object-store read path) and the documented one-liners that read a
given version with pandas, pyarrow, DuckDB and Polars, offline."""

from __future__ import annotations

import re
from pathlib import PurePosixPath

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

import graspcap.catalog as gc
from graspcap.catalog.layout import CatalogLayout
from tests.catalog_factory import make_build
from tests.conftest import REPO

IDS_1 = ["p01-mug-use-00", "p02-drill-use-00"]
IDS_2 = ["p01-mug-use-00", "p03-bowl-use-00"]  # p01 rewritten with other values


@pytest.fixture(scope="module")
def two_versions(tmp_path_factory):
    root = tmp_path_factory.mktemp("urls") / "cat"
    url = root.as_uri()  # file:///...
    cat = gc.open(url, create=True)
    builds = [make_build(IDS_1, seed=1, build_id="b1"), make_build(IDS_2, seed=2, build_id="b2"),
              make_build(["p03-mug-use-01"], seed=3, build_id="b3")]
    assert [cat.commit(b) for b in builds] == [1, 2, 3]
    return root, url, builds


def _keyed(table: pa.Table) -> dict[tuple[str, int], list[float]]:
    return {(r["session_id"], r["frame"]): list(r["T_c_o"])
            for r in table.select(["session_id", "frame", "T_c_o"]).to_pylist()}


def test_file_url_end_to_end(two_versions):
    root, url, builds = two_versions
    cat = gc.open(url)
    assert cat.layout.root == root.resolve() and cat.layout.is_local
    assert gc.open(root).table("frames", 1).equals(cat.table("frames", 1))
    for v, build in ((1, builds[0]), (2, builds[1])):
        for sid in ("p01-mug-use-00",):
            values, observed = cat.contactmap(sid, v)
            np.testing.assert_array_equal(values, build.session_arrays[sid].contact)
            np.testing.assert_array_equal(observed, build.session_arrays[sid].observed)
    ds = gc.GraspDataset(url, version=2, valid_only=False)
    assert len(ds) == 3 * 3 and ds[0]["contact"].dtype == np.float32


def test_object_store_read_path_on_a_file_store(two_versions):
    """The code path of s3:// / gs:// / az:// (deltalake's store + fsspec), run offline on a
    file:// store: tables, file lists and arrays read the same as the local fast path."""
    root, url, builds = two_versions
    remote = gc.Catalog(CatalogLayout(PurePosixPath(root), url=url))
    assert not remote.layout.is_local
    local = gc.open(root)
    strip = remote.layout.fs._strip_protocol
    assert [strip(f) for f in remote.files("frames", 2)] == local.files("frames", 2)
    for name in ("sessions", "frames", "builds"):
        assert remote.table(name, 1).equals(local.table(name, 1)), name
    values, _ = remote.contactmap("p02-drill-use-00", 1)
    np.testing.assert_array_equal(values, builds[0].session_arrays["p02-drill-use-00"].contact)
    verts, faces = remote.hand_mesh("p03-bowl-use-00", 2)
    np.testing.assert_array_equal(faces, builds[1].session_arrays["p03-bowl-use-00"].hand_faces)
    with pytest.raises(gc.CatalogError, match="needs a local catalog"):
        remote.tag(1, "nope")
    with pytest.raises(gc.CatalogError, match="needs a local catalog"):
        remote.commit(make_build(["p09-mug-use-00"], seed=9))


def test_unsupported_urls_say_why():
    with pytest.raises(gc.CatalogError, match="memory:// cannot work"):
        gc.open("memory://cat")
    with pytest.raises(gc.CatalogError, match="ftp:// is not one"):
        gc.open("ftp://host/cat")
    layout = CatalogLayout.from_uri("s3://bucket/graspcap", {"AWS_REGION": "eu-west-1"})
    assert layout.table_uri("frames") == "s3://bucket/graspcap/tables/frames"
    with pytest.raises(gc.CatalogError, match="object store"):
        layout.require_local("commit")


# the one-liners of docs/catalog.md -----------------------------------------------------------
def test_one_liners_read_the_given_version(two_versions):
    root, _, _ = two_versions
    cat = gc.open(root)
    for v in (1, 2):
        want = _keyed(cat.table("frames", v))
        files = gc.open(root).files("frames", v)  # the documented way to pin a version
        assert _keyed(pq.read_table(files)) == want
        df = pd.read_parquet(files)
        assert {(s, f): list(t) for s, f, t in zip(df.session_id, df.frame, df.T_c_o,
                                                   strict=True)} == want
    assert _keyed(cat.table("frames", 1)) != _keyed(cat.table("frames", 2))


def test_duckdb_one_liner_offline(two_versions):
    duckdb = pytest.importorskip("duckdb")
    root, _, _ = two_versions
    cat = gc.open(root)
    con = duckdb.connect(config={"autoinstall_known_extensions": False,
                                 "autoload_known_extensions": False})
    for v in (1, 2):
        files = cat.files("frames", v)
        got = con.read_parquet(files).select("session_id, frame, T_c_o").to_arrow_table()
        assert _keyed(got) == _keyed(cat.table("frames", v))
        n = con.sql(f"SELECT count(*) FROM read_parquet({files!r}) WHERE frame >= 6"
                    ).fetchall()[0][0]
        frames = cat.table("frames", v)["frame"]
        assert n == pc.sum(pc.greater_equal(frames, 6)).as_py()


def test_polars_one_liners(two_versions):
    pl = pytest.importorskip("polars")
    root, _, _ = two_versions
    cat = gc.open(root)
    for v in (1, 2):
        files = cat.files("frames", v)
        df = pl.read_parquet(files)
        assert _keyed(df.to_arrow()) == _keyed(cat.table("frames", v))
        lazy = pl.scan_parquet(files).filter(pl.col("session_id") == "p01-mug-use-00").collect()
        sel = cat.table("frames", v).filter(pc.equal(cat.table("frames", v)["session_id"],
                                                     "p01-mug-use-00"))
        assert _keyed(lazy.to_arrow()) == _keyed(sel)


def test_the_documented_one_liners_run_as_written(two_versions):
    """The one-liner block of docs/catalog.md, run with the catalog's path substituted."""
    pytest.importorskip("duckdb")
    pytest.importorskip("polars")
    root, _, _ = two_versions
    text = (REPO / "docs" / "catalog.md").read_text()
    block = re.search(r"## One-liners.*?```python\n(.*?)```", text, re.S).group(1)
    assert 'files("frames", 3)' in block and "duckdb" in block and "polars" in block
    namespace = {"gc": gc}
    exec(block.replace('"my-catalog"', repr(str(root))), namespace)  # noqa: S102
    want = gc.open(root).table("frames", 3)
    assert namespace["frames"].height == want.num_rows  # the block ends with Polars
    assert namespace["files"] == gc.open(root).files("frames", 3)
