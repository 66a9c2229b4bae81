"""The add-on's background warm-up (pointgt_blender/bridge/warmup.py), without Blender: it loads the models into
the frame renderer's cache and runs one tiny frame; errors are kept, not raised."""
from pointgt_blender.bridge import frame_renderer, warmup
from tests.helpers.tiny import save_tiny


def test_warmup_loads_the_model_into_the_cache(tmp_path):
    path = str(save_tiny(tmp_path / "m.pgt", "fast"))
    frame_renderer.MODELS.clear()
    warmup.done_paths.clear()
    assert warmup.start([(path, "cpu"), (path, "cpu")])
    assert warmup.wait(120)
    assert warmup.done_paths == [path]  # once, though named twice
    key = next(iter(frame_renderer.MODELS._items))
    assert key[0].endswith("m.pgt") and key[1] == "cpu"
    bundle = frame_renderer.MODELS.get(path, "cpu")  # a cache hit: the same object the warm-up loaded
    assert bundle is frame_renderer.MODELS._items[key][1]
    frame_renderer.MODELS.clear()


def test_warmup_keeps_errors_and_skips_empty_lists(tmp_path):
    assert not warmup.start([])
    warmup.last_error = ""
    assert warmup.start([(str(tmp_path / "missing.pgt"), "cpu")])
    assert warmup.wait(120)
    assert "not found" in warmup.last_error


def test_warmup_extracts_packed_models_before_loading_them(tmp_path):
    """A packed model's path does not exist when the warm-up starts: its extraction runs first, in the thread."""
    source = save_tiny(tmp_path / "m.pgt", "fast")
    target = tmp_path / "extracted" / "sha.pgt"
    calls = []

    def extract():
        calls.append(target.exists())
        target.parent.mkdir()
        target.write_bytes(source.read_bytes())
        return str(target)

    frame_renderer.MODELS.clear()
    warmup.done_paths.clear()
    warmup.last_error = ""
    assert warmup.start([(str(target), "cpu")], extract=[extract])
    assert warmup.wait(120)
    assert calls == [False] and warmup.last_error == "" and warmup.done_paths == [str(target)]
    frame_renderer.MODELS.clear()
