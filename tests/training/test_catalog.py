"""The catalogue's clips for every task: plain and gzipped BVH alike, by activity and by source."""

from pathlib import Path

from training.data.catalog import mocap_entries


def test_clips_are_found_plain_and_gzipped_and_filtered_by_source(data_dir: Path) -> None:
    walks = mocap_entries(data_dir, ["walk"])
    sources = {e.source for e in walks}
    assert {"cmu_iclone", "cmu_li2018", "bandai_namco_1", "bandai_namco_2"} <= sources, sources
    assert any(e.path.endswith(".bvh.gz") for e in walks) and any(e.path.endswith(".bvh") for e in walks)
    assert all(e.activity == "walk" and not e.exclude for e in walks)
    cmu = mocap_entries(data_dir, ["walk"], ["cmu_iclone", "cmu_li2018", "cmu_raw"])
    assert cmu and {e.source for e in cmu} <= {"cmu_iclone", "cmu_li2018", "cmu_raw"}
    assert len(cmu) < len(walks)
    assert mocap_entries(data_dir, sources=["no_such_source"]) == []
