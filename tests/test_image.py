import cv2
import numpy as np
import pytest

from dvpmvs.image import ImageReadError, image_gradient, read_image, sample_bilinear


def numpy_bilinear(image, x, y, fill):
    h, w = image.shape
    out = np.full(x.shape, fill, np.float64)
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    xi, yi = x[inside], y[inside]
    x0 = np.floor(xi).astype(int)
    y0 = np.floor(yi).astype(int)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    ax, ay = xi - x0, yi - y0
    out[inside] = ((1 - ay) * ((1 - ax) * image[y0, x0] + ax * image[y0, x1])
                   + ay * ((1 - ax) * image[y1, x0] + ax * image[y1, x1]))
    return out


def test_bilinear_sampler_matches_numpy_reference():
    rng = np.random.default_rng(0)
    image = rng.uniform(size=(31, 47)).astype(np.float32)
    x = rng.uniform(-2, 49, (200, 3))
    y = rng.uniform(-2, 33, (200, 3))
    got = sample_bilinear(image, x, y, fill=-1.0)
    np.testing.assert_allclose(got, numpy_bilinear(image, x, y, -1.0), atol=1e-5)
    assert got.shape == (200, 3)


def test_bilinear_sampler_is_exact_at_pixel_centres_and_rejects_nan():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert sample_bilinear(image, 2.0, 1.0) == image[1, 2]
    assert sample_bilinear(image, 3.0, 2.0) == image[2, 3]  # last pixel, no out-of-bounds read
    assert sample_bilinear(image, 0.5, 0.0) == pytest.approx(0.5)
    assert np.isnan(sample_bilinear(image, np.nan, 0.0))
    assert sample_bilinear(image, 3.01, 0.0, fill=7.0) == 7.0


def test_bilinear_sampler_agrees_with_opencv_remap():
    rng = np.random.default_rng(1)
    image = rng.uniform(size=(40, 50)).astype(np.float32)
    x = rng.uniform(0, 49, (20, 20)).astype(np.float32)
    y = rng.uniform(0, 39, (20, 20)).astype(np.float32)
    ref = cv2.remap(image, x, y, cv2.INTER_LINEAR)
    # OpenCV quantises the fractional position to 1/32 pixel.
    np.testing.assert_allclose(sample_bilinear(image, x, y), ref, atol=2e-2)


def test_gradient_matches_numpy():
    rng = np.random.default_rng(2)
    image = rng.uniform(size=(20, 30)).astype(np.float32)
    gx, gy = image_gradient(image)
    ref_gy, ref_gx = np.gradient(image)
    np.testing.assert_allclose(gx, ref_gx, atol=1e-6)
    np.testing.assert_allclose(gy, ref_gy, atol=1e-6)


def test_read_image_formats(tmp_path):
    grey16 = (np.arange(20, dtype=np.uint16).reshape(4, 5) * 3000)
    cv2.imwrite(str(tmp_path / "g.png"), grey16)
    image = read_image(tmp_path / "g.png")
    assert image.shape == (4, 5, 3)
    np.testing.assert_allclose(image[..., 1], grey16 / 65535.0, atol=1e-6)
    bgr = np.zeros((2, 2, 3), np.uint8)
    bgr[..., 2] = 255  # red in OpenCV's BGR order
    cv2.imwrite(str(tmp_path / "r.png"), bgr)
    assert read_image(tmp_path / "r.png")[0, 0].tolist() == [1.0, 0.0, 0.0]
    with pytest.raises(ImageReadError, match="not found"):
        read_image(tmp_path / "none.png")
