import cv2
import numpy as np
import pytest

from dvpmvs.image import (
    ImageReadError,
    image_gradient,
    noise_sigma,
    read_image,
    sample_bilinear,
    smooth_untextured,
)

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


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
    out[inside] = (1 - ay) * ((1 - ax) * image[y0, x0] + ax * image[y0, x1]) + ay * (
        (1 - ax) * image[y1, x0] + ax * image[y1, x1]
    )
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
    grey16 = np.arange(20, dtype=np.uint16).reshape(4, 5) * 3000
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


def _textured(shape, seed):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 1.0)


@pytest.mark.parametrize("sigma", [0.005, 0.02])
def test_noise_sigma_finds_the_added_noise_under_texture(sigma):
    image = np.zeros((120, 160), np.float32)
    image[:, :120] = 0.3 + np.linspace(0, 0.2, 120)[None, :]  # shading: no response
    image[:, 120:] = _textured((120, 40), 1)  # texture on a quarter: a minority of strong responses
    noisy = image + np.random.default_rng(2).normal(0, sigma, image.shape).astype(np.float32)
    assert noise_sigma(noisy) == pytest.approx(sigma, rel=0.2)
    assert noise_sigma(image[:, :120]) < 1e-4


def test_smooth_untextured_smooths_flat_areas_and_keeps_texture():
    rng = np.random.default_rng(3)
    image = np.full((100, 200), 0.5, np.float32)
    image[:, 100:] = 0.2 + 0.6 * (
        (3 * _textured((100, 100), 4)) % 1.0
    )  # strong texture on the right
    noisy = image + rng.normal(0, 0.01, image.shape).astype(np.float32)
    out = smooth_untextured(noisy, 1.0)
    flat, textured = (slice(10, 90), slice(10, 90)), (slice(10, 90), slice(110, 190))
    assert np.std(out[flat] - 0.5) < 0.4 * np.std(noisy[flat] - 0.5)  # noise averaged away
    # Detail kept: the texture's deviation from its own Gaussian mean survives almost whole.
    detail_in = noisy - cv2.GaussianBlur(noisy, (0, 0), 1.0)
    detail_out = out - cv2.GaussianBlur(noisy, (0, 0), 1.0)
    assert np.abs(detail_out[textured]).mean() > 0.8 * np.abs(detail_in[textured]).mean()
    assert np.array_equal(smooth_untextured(noisy, 0.0), noisy)
    # A larger noise_scale smooths more of the texture too.
    more = smooth_untextured(noisy, 1.0, noise_scale=20.0)
    assert (
        np.abs(more[textured] - noisy[textured]).mean()
        > np.abs(out[textured] - noisy[textured]).mean()
    )


def test_smooth_untextured_rejects_bad_arguments():
    with pytest.raises(ValueError, match="single-channel"):
        smooth_untextured(np.zeros((4, 4, 3), np.float32), 1.0)
    with pytest.raises(ValueError, match=">= 0"):
        smooth_untextured(np.zeros((4, 4), np.float32), -1.0)
