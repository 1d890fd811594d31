"""Expression spaces: names, parsing, ARKit mapping, FLAME axis-angle -> 6D."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from fastgha_core.expressions import (
    ARKIT52_NAMES,
    arkit_to_ict53,
    flame120_from_axis_angle,
    get_space,
    rotation_6d_to_matrix,
)
from fastgha_core.rotations import axis_angle_to_matrix, matrix_to_rotation_6d

ICT_NPZ = Path(__file__).resolve().parents[1] / "fastgha_core" / "assets" / "headmodel" / "ict_facekit.npz"  # shipped


def test_ict53_names_match_the_archive_when_available():
    ict = get_space("ict53")
    assert ict.dim == 53 and len(set(ict.names)) == 53
    assert ict.names[0] == "browDown_L" and ict.names[-1] == "noseSneer_R"
    archive = [str(n) for n in np.load(ICT_NPZ)["expression_names"]]
    assert ict.names == archive


def test_flame120_layout_and_neutral():
    f = get_space("flame120")
    assert f.dim == 120
    assert f.names[0] == "expr_000" and f.names[99] == "expr_099"
    assert f.names[100:106] == [f"jaw_r6d_{i}" for i in range(6)]
    assert f.names[106] == "eyeL_r6d_0" and f.names[112] == "eyeR_r6d_0"
    assert f.names[118:] == ["eyelid_L", "eyelid_R"]
    n = f.neutral()
    expected = torch.zeros(120)
    for s in (100, 106, 112):
        expected[s] = 1.0  # R00
        expected[s + 4] = 1.0  # R11
    assert torch.equal(n, expected)
    assert torch.equal(get_space("ict53").neutral(), torch.zeros(53))


def test_parse_vectors():
    ict = get_space("ict53")
    v = [0.1 * (i % 7) for i in range(53)]
    expected = torch.tensor(v, dtype=torch.float32)
    for value in (v, tuple(v), np.asarray(v), torch.tensor(v, dtype=torch.float64)):
        out = ict.parse(value)
        assert out.dtype == torch.float32 and out.shape == (53,)
        assert_close(out, expected)


@pytest.mark.parametrize(
    "value, pattern",
    [
        ([0.0] * 52, r"'ict53'.*expected a vector of 53 values, got shape \[52\]"),
        ([[0.0] * 53], r"'ict53'.*got shape \[1, 53\]"),
        ([0.0] * 52 + [float("nan")], r"'ict53'.*finite, got nan at index 52 \(noseSneer_R\)"),
        (["a"] * 53, r"'ict53'.*non-numeric"),
        ({"jawOpen": "wide"}, r"'ict53'.*weight for 'jawOpen' must be a number, got str"),
        ({"jawOpen": None}, r"'ict53'.*must be a number, got NoneType"),
        ({"jawOpen": float("inf")}, r"'ict53'.*must be finite, got inf"),
        ({"smile": 1.0, "jawOpen": 0.2}, r"'ict53'.*unknown name\(s\) \['smile'\]"),
        ({3: 1.0}, r"'ict53'.*names must be strings"),
        ("jawOpen", r"'ict53'.*expected a vector of 53 numbers or a name->weight map, got str"),
    ],
)
def test_parse_errors_name_the_space(value, pattern):
    with pytest.raises(ValueError, match=pattern):
        get_space("ict53").parse(value)


def test_flame120_errors_name_the_space():
    with pytest.raises(ValueError, match=r"'flame120'.*expected a vector of 120 values, got shape \[53\]"):
        get_space("flame120").parse([0.0] * 53)
    with pytest.raises(ValueError, match=r"'flame120'.*unknown name"):
        get_space("flame120").parse({"jawOpen": 1.0})
    with pytest.raises(ValueError, match=r"unknown expression space 'arkit'; expected one of \['ict53', 'flame120'\]"):
        get_space("arkit")


def test_parse_map_ict_names_and_missing_are_neutral():
    ict = get_space("ict53")
    out = ict.parse({"jawOpen": 0.7, "eyeBlink_R": 1})
    expected = torch.zeros(53)
    expected[26] = 0.7  # jawOpen is the 27th archive name
    expected[11] = 1.0  # eyeBlink_R
    assert_close(out, expected)
    # flame120: missing names keep their neutral value (identity rotation for 6D blocks)
    f = get_space("flame120")
    code = f.parse({"expr_003": -1.5, "eyelid_R": 0.25})
    exp = f.neutral()
    exp[3] = -1.5
    exp[119] = 0.25
    assert_close(code, exp)


def test_arkit_mapping():
    weights = {
        "eyeBlinkLeft": 0.9,  # -> eyeBlink_L (index 10)
        "mouthSmileRight": 0.4,  # -> mouthSmile_R (46)
        "browInnerUp": 0.6,  # -> browInnerUp_L (2) and _R (3)
        "cheekPuff": 0.3,  # -> cheekPuff_L (6) and _R (7)
        "jawOpen": 0.5,  # same name (26)
        "jawLeft": 0.2,  # same name, not a Left/Right pair (25)
        "tongueOut": 1.0,  # dropped
        "_neutral": 0.1,  # MediaPipe's extra category, dropped
        "NoseSneerLeft": 0.8,  # Live Link Face capitalisation -> noseSneer_L (51)
    }
    out = arkit_to_ict53(weights)
    expected = torch.zeros(53)
    for i, w in [(10, 0.9), (46, 0.4), (2, 0.6), (3, 0.6), (6, 0.3), (7, 0.3), (26, 0.5), (25, 0.2), (51, 0.8)]:
        expected[i] = w
    assert_close(out, expected)


def test_every_arkit_name_is_accepted_and_all_ict_shapes_reachable():
    ict = get_space("ict53")
    assert len(ARKIT52_NAMES) == 52 and len(set(ARKIT52_NAMES)) == 52
    code = ict.parse({n: 1.0 for n in ARKIT52_NAMES})
    assert torch.equal(code, torch.ones(53))  # 51 names drive all 53 ICT shapes; tongueOut dropped


def test_conflicting_names_rejected():
    with pytest.raises(ValueError, match=r"'browInnerUp_L' is set twice \(by 'browInnerUp' and 'browInnerUp_L'\)"):
        get_space("ict53").parse({"browInnerUp": 0.5, "browInnerUp_L": 0.1})


def test_parse_batch():
    ict = get_space("ict53")
    b = ict.parse_batch([{"jawOpen": 1.0}, [0.5] * 53])
    assert b.shape == (2, 53) and b[0, 26] == 1.0 and b[0].sum() == 1.0 and torch.all(b[1] == 0.5)
    assert ict.parse_batch(torch.zeros(3, 53)).shape == (3, 53)
    assert ict.parse_batch([]).shape == (0, 53)
    with pytest.raises(ValueError, match=r"'ict53'.*expected a \[B, 53\] batch, got shape \[53\]"):
        ict.parse_batch(torch.zeros(53))


# ---------------------------------------------------------------- rotations / flame120
def test_axis_angle_and_6d_by_hand():
    # 90° about z: R = [[0,-1,0],[1,0,0],[0,0,1]]; first two columns (0,1,0), (-1,0,0)
    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    assert_close(R, torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64), atol=1e-12, rtol=0)
    assert_close(matrix_to_rotation_6d(R), torch.tensor([0.0, 1, 0, -1, 0, 0], dtype=torch.float64), atol=1e-12, rtol=0)
    # 90° about x: R = [[1,0,0],[0,0,-1],[0,1,0]] -> 6D (1,0,0, 0,0,1)
    Rx = axis_angle_to_matrix(torch.tensor([math.pi / 2, 0.0, 0.0], dtype=torch.float64))
    assert_close(matrix_to_rotation_6d(Rx), torch.tensor([1.0, 0, 0, 0, 0, 1], dtype=torch.float64), atol=1e-12, rtol=0)


def test_rotation_6d_inverse_and_gram_schmidt():
    g = torch.Generator().manual_seed(0)
    aa = torch.randn(32, 3, generator=g, dtype=torch.float64)
    R = axis_angle_to_matrix(aa)
    assert_close(rotation_6d_to_matrix(matrix_to_rotation_6d(R)), R, atol=1e-12, rtol=0)
    # A non-orthonormal 6D input is orthonormalised: a1 = (2,0,0), a2 = (1,3,0) -> columns x, y, z
    out = rotation_6d_to_matrix(torch.tensor([2.0, 0, 0, 1, 3, 0], dtype=torch.float64))
    assert_close(out, torch.eye(3, dtype=torch.float64))


def test_rodrigues_gradient_finite_at_zero():
    aa = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    R = axis_angle_to_matrix(aa)
    R[1, 0].backward()  # d R10 / d w_z = 1 at the identity
    assert torch.isfinite(aa.grad).all()
    assert_close(aa.grad, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_flame120_from_axis_angle_by_hand():
    T = 2
    expr = torch.arange(T * 50, dtype=torch.float32).reshape(T, 50) / 100  # 50 coefficients: zero-padded to 100
    jaw = torch.tensor([[0.0, 0.0, math.pi / 2], [0.0, 0.0, 0.0]])
    eyes = torch.tensor([[math.pi / 2, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2]])
    lids = torch.tensor([[0.1, 0.2], [0.3, 0.4]])
    out = flame120_from_axis_angle(expr, jaw, eyes, lids)
    assert out.shape == (T, 120)
    assert_close(out[:, :50], expr)
    assert torch.equal(out[:, 50:100], torch.zeros(T, 50))
    ident, rz, rx = [1.0, 0, 0, 0, 1, 0], [0.0, 1, 0, -1, 0, 0], [1.0, 0, 0, 0, 0, 1]
    assert_close(out[0, 100:106], torch.tensor(rz), atol=1e-6, rtol=0)  # jaw
    assert_close(out[0, 106:112], torch.tensor(rx), atol=1e-6, rtol=0)  # left eye
    assert_close(out[0, 112:118], torch.tensor(ident))  # right eye
    assert_close(out[1, 100:106], torch.tensor(ident))
    assert_close(out[1, 112:118], torch.tensor(rz), atol=1e-6, rtol=0)
    assert_close(out[:, 118:], lids)
    # No eyelids -> zeros; zero pose -> exactly the neutral code
    neutral = flame120_from_axis_angle(torch.zeros(100), torch.zeros(3), torch.zeros(6))
    assert torch.equal(neutral, get_space("flame120").neutral())
    get_space("flame120").parse(out[0])  # a valid code of the space
    with pytest.raises(ValueError, match=r"eyes must have shape \[\.\.\., 6\], got \[2, 3\]"):
        flame120_from_axis_angle(expr, jaw, eyes[:, :3])
    with pytest.raises(ValueError, match=r"expr must have shape \[\.\.\., <=100\], got \[2, 101\]"):
        flame120_from_axis_angle(torch.zeros(T, 101), jaw, eyes)
    with pytest.raises(ValueError, match=r"jaw must share the leading shape \[2\]"):
        flame120_from_axis_angle(expr, jaw[:1], eyes)


def test_live_link_face_pose_names_are_explained_not_just_unknown():
    """A Live Link Face frame forwarded as is carries HeadYaw & co. beside the 52 shapes: the error
    says what they are and what to do, and real typos keep the plain message."""
    space = get_space("ict53")
    with pytest.raises(ValueError, match=r"unknown name\(s\) \['HeadYaw', 'LeftEyePitch'\].*head/eye rotations of Live Link Face.*with the camera"):
        space.parse({"EyeBlinkLeft": 1.0, "HeadYaw": 0.1, "LeftEyePitch": 0.0})
    with pytest.raises(ValueError) as e:
        space.parse({"jawOpenn": 1.0})
    assert "Live Link" not in str(e.value)


def test_side_less_names_say_which_sided_names_to_send():
    """``eyeBlink`` / ``mouthSmile`` are what a user types for a blink or a smile; the shapes come per
    side, and the error names the pair to send (ARKit's names in ict53); a name with no sided pair,
    or a space without per-side shapes (flame120), keeps the plain message."""
    space = get_space("ict53")
    with pytest.raises(ValueError, match=r"'eyeBlink' comes per side: 'eyeBlinkLeft' and 'eyeBlinkRight'.*'mouthSmile' comes per side: 'mouthSmileLeft' and 'mouthSmileRight'"):
        space.parse({"eyeBlink": 1.0, "mouthSmile": 1.0, "jawOpen": 0.2})
    assert_close(space.parse({"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0}), space.parse({"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}))
    with pytest.raises(ValueError) as e:
        space.parse({"smile": 1.0})
    assert "per side" not in str(e.value)
    with pytest.raises(ValueError) as e:
        get_space("flame120").parse({"eyeBlink": 1.0})
    assert "per side" not in str(e.value)


@pytest.mark.parametrize(
    "typo, meant",
    [
        ("jawOpne", "jawOpen"),  # a transposition
        ("jaw_open", "jawOpen"),  # snake case of an accepted name
        ("JAWOPEN", "jawOpen"),  # capitals
        ("eyeBlinkLeftt", "eyeBlinkLeft"),  # an ARKit alias, one letter too many
        ("mouthSmile_l", "mouthSmile_L"),  # an ict53 name, side in lower case
    ],
)
def test_a_misspelt_name_gets_a_did_you_mean(typo, meant):
    """A typo in a name (the server's ``unknown_expression_name``, ``fastgha animate``/``client``
    ``--expressions``, the browser demo's sequences) names the accepted name it is closest to; the
    name is still refused (no guessing on the wire)."""
    with pytest.raises(ValueError, match=rf"unknown name\(s\) \[{typo!r}\].*did you mean {meant!r} for {typo!r}"):
        get_space("ict53").parse({typo: 1.0, "jawLeft": 0.2})


def test_names_far_from_any_accepted_one_get_no_guess():
    with pytest.raises(ValueError) as e:
        get_space("ict53").parse({"smile": 1.0, "zzz": 0.5})
    assert "did you mean" not in str(e.value)
    with pytest.raises(ValueError) as e:  # a pose of Live Link Face and a side-less name keep their own hints only
        get_space("ict53").parse({"HeadYaw": 0.1, "eyeBlink": 1.0})
    assert "did you mean" not in str(e.value) and "Live Link" in str(e.value) and "per side" in str(e.value)


def test_a_word_inside_accepted_names_lists_them():
    """What a new user types for a smile or a blink ("smile", "Blink") is no typo of one name: the
    message lists the space's names that contain it (still refused), and nothing for a word no name holds."""
    with pytest.raises(ValueError, match=r"names containing 'smile': \['mouthSmile_L', 'mouthSmile_R'\]$"):
        get_space("ict53").parse({"smile": 1.0})
    with pytest.raises(ValueError, match=r"names containing 'Blink': \['eyeBlink_L', 'eyeBlink_R'\]$"):
        get_space("ict53").parse({"Blink": 1.0})
    with pytest.raises(ValueError) as e:
        get_space("ict53").parse({"zzz": 1.0, "ab": 1.0})
    assert "containing" not in str(e.value) and "did you mean" not in str(e.value)


def test_side_less_names_in_other_cases_say_which_sided_names_to_send():
    """``eyeblink`` / ``mouth_smile`` (case and ``_`` aside, a side-less name) get the per-side hint,
    not a guess of one side."""
    with pytest.raises(ValueError, match=r"'eyeblink' comes per side: 'eyeBlinkLeft' and 'eyeBlinkRight'.*'mouth_smile' comes per side: 'mouthSmileLeft' and 'mouthSmileRight'") as e:
        get_space("ict53").parse({"eyeblink": 1.0, "mouth_smile": 1.0})
    assert "did you mean" not in str(e.value)


def test_refusing_unknown_names_stays_cheap():
    """The server answers every frame message; one with many unknown (or huge) names must not cost
    more to refuse because of the suggestion: the lookup (dictionary probes, no pairwise string
    comparison) runs for the first typo only, once per message, and a name longer than any accepted
    one is not compared at all. Also: a typo of a name accepted and ignored (tongueOut) is named."""
    space = get_space("ict53")
    calls = []
    real = type(space)._closest

    def counting(self, key):
        calls.append(key)
        return real(self, key)

    try:
        type(space)._closest = counting
        with pytest.raises(ValueError, match=r"did you mean 'jawOpen' for 'jawOpne'\?$"):
            space.parse({"jawOpne": 0.1, **{f"eyeBlinkLef{i}": 0.1 for i in range(7)}, "x" * 30_000: 1.0})
    finally:
        type(space)._closest = real
    assert calls == ["jawOpne"]
    assert space._closest("x" * 30_000) is None
    assert space._closest("tongueOutt") == "tongueOut"
