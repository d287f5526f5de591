import numpy as np

from odmv.data.dataset import check_spec, load_scene, split_scenes
from odmv.io.manifest import load_manifest
from odmv.study import coverage as view_coverage


def test_one_view_misses_the_first_view_subsets_and_four_views_miss_nothing(tiny_dataset):
    n, counts = view_coverage.coverage(str(tiny_dataset), "train")
    m = load_manifest(tiny_dataset)
    ids = split_scenes(m, None, 0)["train"]
    assert n == len(ids) > 0
    # the dataset's first-view subsets, counted by the data pipeline's own code
    spec = check_spec(m, m.views, [m.height_px, m.width_px], None, None)
    scenes = [load_scene(m, sid, spec) for sid in ids]
    valid = sum(int(np.isfinite(s["depth_mm"]).sum()) for s in scenes)
    hidden = sum(int((s["first_unlit"] & np.isfinite(s["depth_mm"])).sum()) for s in scenes)
    occluded = sum(int((s["first_shadowed"] & np.isfinite(s["depth_mm"])).sum()) for s in scenes)
    assert list(counts[1]) == [valid, occluded, hidden - occluded]
    # each projector lights a band of the field: one view misses a large part of it, every
    # added view less, four views nothing that some projector lights
    missed = {s: c[1] + c[2] for s, c in counts.items()}
    assert missed[1] > 0.15 * valid and missed[1] > missed[2] >= missed[3] > missed[4] == 0
