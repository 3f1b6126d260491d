"""kernels.motion: the whole image's shift between two frames, against OpenCV's
phaseCorrelate and against the shift that made the second frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from checks import check_kernel

from cpf_jax.kernels import color, motion
from cpf_jax.synthetic import make_sequence

SHIFTS = [(5.0, 0.0), (-7.5, 3.25), (12.0, -9.0), (0.4, 0.0), (-20.0, 14.5)]


@pytest.fixture(scope="module")
def room():
    return make_sequence("walk_across_medium", n_frames=1).colour[0]


def _moved(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    size = (image.shape[1], image.shape[0])
    return cv2.warpAffine(image, m, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _grey64(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float64)


def test_grey_is_opencvs_luma(room):
    check_kernel(
        color.grey,
        lambda c: cv2.cvtColor(np.asarray(c), cv2.COLOR_RGB2GRAY).astype(np.float32),
        (room,),
        batch=[(room,), (room[::-1].copy(),)],
        atol=0.51,  # OpenCV rounds to uint8
    )


@pytest.mark.parametrize(("dx", "dy"), SHIFTS)
def test_phase_correlation_finds_the_shift_as_opencv_does(room, dx, dy):
    a, b = _grey64(room), _grey64(_moved(room, dx, dy))
    window = cv2.createHanningWindow(a.shape[::-1], cv2.CV_64F)
    (ref_dx, ref_dy), _ = cv2.phaseCorrelate(a, b, window)

    def truth(a, b):
        return np.array([dx, dy], np.float32)

    # Against the shift that made b: a third of a pixel (OpenCV's own error here is 0.3).
    shifted = [(a, b), (b, a)]
    check_kernel(
        lambda a, b: motion.phase_correlation(a, b)[0],
        truth,
        (a, b),
        batch=[shifted[0], shifted[0]],
        atol=0.34,
    )
    ours = np.asarray(motion.phase_correlation(a, b)[0])
    np.testing.assert_allclose(ours, [ref_dx, ref_dy], atol=0.34)
    back = np.asarray(motion.phase_correlation(b, a)[0])
    np.testing.assert_allclose(back, -ours, atol=0.05)  # the other way round


def test_frame_motion_downscaled_and_its_peak(room):
    moved = _moved(room, -16.0, 6.0)
    shift, peak = motion.frame_motion(room, moved, factor=4)
    np.testing.assert_allclose(np.asarray(shift), [-16.0, 6.0], atol=0.5)
    assert float(peak) > 0.5
    noise = np.random.default_rng(0).integers(0, 256, room.shape, dtype=np.uint8)
    _, unrelated = motion.frame_motion(room, noise, factor=4)
    assert float(unrelated) < 0.1 < float(peak)


def test_downscale_is_block_means():
    image = np.arange(7 * 9, dtype=np.float32).reshape(7, 9)
    check_kernel(
        lambda x: motion.downscale(x, 3),
        lambda x: np.asarray(x)[:6, :9].reshape(2, 3, 3, 3).mean(axis=(1, 3)),
        (image,),
        batch=[(image,), (image * 2,)],
    )
