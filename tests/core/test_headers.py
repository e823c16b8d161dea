"""Image decoders on malformed files: every format, truncated (in the header and in the pixels),
wrong magic bytes, empty, without pixels and with huge dimensions, each refused with a message
that says which and never names the file's path; the pixel limit is read from the header."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bad_inputs import EXTS, HUGE, bad_variants, good_image, png_header  # noqa: E402

from core.data.headers import default_max_pixels, read_header, set_default_max_pixels
from core.data.images import ImageReadError, image_size, read_image, verify_image

CASES = [(reader, fmt, name) for reader in (read_image, verify_image) for fmt in EXTS
         for name in ("truncated header", "truncated pixels", "wrong magic", "empty",
                      "no pixels", "huge")
         # libjpeg fills a truncated scan with grey: validation (verify_image) is the proof
         if (reader, fmt, name) != (read_image, "jpeg", "truncated pixels")]


@pytest.mark.parametrize("reader, fmt, case", CASES)
def test_each_decoder_refuses_each_malformed_file(tmp_path, reader, fmt, case):
    data, words = bad_variants(fmt, good_image(fmt, tmp_path))[case]
    path = tmp_path / f"bad{EXTS[fmt]}"
    path.write_bytes(data)
    with pytest.raises(ImageReadError) as err:
        reader(path)
    assert words in err.value.message, err.value.message
    assert str(tmp_path) not in err.value.message
    assert err.value.path == path


@pytest.mark.parametrize("fmt", list(EXTS))
def test_good_files_read_and_the_limit_comes_from_the_header(tmp_path, fmt):
    path = tmp_path / f"ok{EXTS[fmt]}"
    path.write_bytes(good_image(fmt, tmp_path, 64, 32))
    assert read_image(path).shape[:2] == (32, 64)
    assert verify_image(path)[:2] == (64, 32) and image_size(path) == (64, 32)
    with pytest.raises(ImageReadError, match="is 64x32 \\(2048 pixels\\); the limit is 2047"):
        verify_image(path, max_pixels=2047)
    assert read_image(path, max_pixels=2048).shape[:2] == (32, 64)


def test_huge_headers_are_read_without_decoding(tmp_path):
    path = tmp_path / "huge.png"
    path.write_bytes(png_header(*HUGE))
    header = read_header(path)
    assert (header.width, header.height, header.format) == (*HUGE, "png")
    assert image_size(path) == HUGE  # the size alone is no decode: no limit applies


def test_the_process_default_limit_is_settable(tmp_path):
    path = tmp_path / "ok.png"
    path.write_bytes(good_image("png", tmp_path, 64, 32))
    before = default_max_pixels()
    try:
        set_default_max_pixels(100)
        with pytest.raises(ImageReadError, match="the limit is 100 pixels"):
            read_image(path)
    finally:
        set_default_max_pixels(before)
    with pytest.raises(ValueError, match="positive"):
        set_default_max_pixels(0)


def test_extension_and_content_must_agree(tmp_path):
    path = tmp_path / "photo.png"
    path.write_bytes(good_image("jpeg", tmp_path))
    with pytest.raises(ImageReadError, match="not a PNG file"):
        verify_image(path)
    with pytest.raises(ImageReadError, match="unsupported file type '.gif'"):
        read_image(tmp_path / "x.gif")


def test_images_that_importers_convert_are_checked_from_their_header(synth_capture, tmp_path):
    """BMP/TIFF/WebP/PPM sources are converted to PNG on import: their header is read first,
    so a huge one is refused before OpenCV would decode it."""
    import json

    from bad_inputs import bmp_header

    from core.data import CaptureError, import_capture, load_capture
    from core.data.headers import HeaderError, read_other_header
    from core.data.importers.transforms import export_transforms

    path = tmp_path / "huge.bmp"
    path.write_bytes(bmp_header(*HUGE))
    assert read_other_header(path) == HUGE
    path.write_bytes(bmp_header(*HUGE)[:20])
    with pytest.raises(HeaderError, match="truncated or corrupt BMP header"):
        read_other_header(path)
    src = tmp_path / "src"
    export_transforms(load_capture(synth_capture), src)
    doc = json.loads((src / "transforms.json").read_text())
    first = doc["frames"][0]
    image = src / first["file_path"]
    image.unlink()
    first["file_path"] = str(Path(first["file_path"]).with_suffix(".bmp"))
    (src / first["file_path"]).write_bytes(bmp_header(*HUGE))
    (src / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(CaptureError) as err:
        import_capture(src, tmp_path / "out", "transforms", max_pixels=1000)
    problem = err.value.problems[0]
    assert problem.path.endswith(".bmp") and f"is {HUGE[0]}x{HUGE[1]}" in problem.message
