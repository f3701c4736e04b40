import cv2
import numpy as np
import pytest

from popcode_runtime import PopcodeError, crop_batch, crop_square, read_image, to_grey


def square_scene(height=200, width=300, box=(100, 50, 40, 40)):
    image = np.zeros((height, width), np.uint8)
    x, y, w, h = box
    image[y : y + h, x : x + w] = 255
    return image


def test_crop_centres_the_box_with_padding():
    crop = crop_square(to_grey(square_scene()), (100, 50, 40, 40))
    assert crop.shape == (128, 128) and crop.dtype == np.float32
    # The 40 px square fills 1/1.1 of the 44 px crop, centred.
    ys, xs = np.nonzero(crop > 0.5)
    assert abs(xs.mean() - 63.5) < 1.0 and abs(ys.mean() - 63.5) < 1.0
    assert (xs.max() - xs.min() + 1) == pytest.approx(128 / 1.1, abs=3)


def test_non_square_box_uses_the_longer_side():
    image = np.zeros((200, 300), np.uint8)
    image[80:100, 100:180] = 255  # 80 x 20 bar
    crop = crop_square(to_grey(image), (100, 80, 80, 20))
    ys, xs = np.nonzero(crop > 0.5)
    assert (xs.max() - xs.min() + 1) == pytest.approx(128 / 1.1, abs=3)
    assert (ys.max() - ys.min() + 1) == pytest.approx(128 / 1.1 / 4, abs=3)


def test_partly_outside_box_is_zero_filled():
    image = np.full((100, 100), 255, np.uint8)
    crop = crop_square(to_grey(image), (-20, 30, 40, 40))
    # Left part of the crop falls outside the image: zeros there, ones inside.
    assert crop[:, :30].max() == 0.0
    assert crop[:, 80:].min() == pytest.approx(1.0)


def test_box_wholly_outside_or_degenerate_is_an_error():
    grey = to_grey(square_scene())
    with pytest.raises(PopcodeError, match="wholly outside"):
        crop_square(grey, (400, 10, 20, 20))
    with pytest.raises(PopcodeError, match="empty"):
        crop_square(grey, (10, 10, 0, 20))
    with pytest.raises(PopcodeError, match="NaN"):
        crop_square(grey, (10, np.nan, 5, 20))
    with pytest.raises(PopcodeError, match="4 numbers"):
        crop_square(grey, (10, 10, 5))


def test_large_box_downscales_without_aliasing():
    # A fine checkerboard averages to grey instead of aliasing to a pattern.
    image = (np.indices((1000, 1000)).sum(axis=0) % 2 * 255).astype(np.uint8)
    crop = crop_square(to_grey(image), (100, 100, 800, 800))
    assert abs(crop.mean() - 0.5) < 0.02 and crop.std() < 0.05


def test_image_validation():
    with pytest.raises(PopcodeError, match="NaN"):
        to_grey(np.full((4, 4), np.nan, np.float32))
    with pytest.raises(PopcodeError, match=r"\[0, 1\]"):
        to_grey(np.full((4, 4), 2.0, np.float32))
    with pytest.raises(PopcodeError, match="dtype"):
        to_grey(np.zeros((4, 4), np.int32))
    with pytest.raises(PopcodeError, match="shape"):
        to_grey(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(PopcodeError, match="numpy array"):
        to_grey([[0, 1]])


def test_grey_conversion_and_bit_depths():
    np.testing.assert_allclose(to_grey(np.full((2, 2), 65535, np.uint16)), 1.0)
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[..., 1] = 255  # pure green
    np.testing.assert_allclose(to_grey(rgb), 0.587, atol=1e-6)


def test_read_image_matches_in_memory(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, size=(30, 40, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "x.png"), rgb[..., ::-1])  # OpenCV writes BGR
    np.testing.assert_allclose(read_image(tmp_path / "x.png"), to_grey(rgb), atol=1e-6)
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(PopcodeError, match="cannot read"):
        read_image(tmp_path / "bad.png")
    with pytest.raises(PopcodeError, match="not found"):
        read_image(tmp_path / "missing.png")


def test_crop_batch_shape():
    crops = crop_batch(square_scene(), [(100, 50, 40, 40), (0, 0, 10, 10)])
    assert crops.shape == (2, 1, 128, 128) and crops.dtype == np.float32
    with pytest.raises(PopcodeError, match="no boxes"):
        crop_batch(square_scene(), [])
