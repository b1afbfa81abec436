"""Learning from pictures: the end marker, DrQ's random shift, the keypoint encoder, and image learners that resume
exactly and train their critic's encoder."""
import json

import pytest
import torch

from agents import ppo, sac
from agents.common.checkpoints import CHECKPOINT
from agents.common.config import load_config
from agents.models.networks import KeypointCNN, random_shift, shift_images
from diffdlo.tasks import image as rimage
from diffdlo.envs import BatchedShapeControl

from tests.test_agents import argv


def straight_and_reversed(env):
    """The env's first rope laid exactly on its straight target, and the same rope the other way round."""
    env.reset(seed=0)
    target = env.get_state().target[0]
    env.set_state(pos=torch.stack([target, target.flip(0)]))
    return env.observe()


@pytest.mark.parametrize("obs_type", ["image", "image_single"])
def test_mark_end_tells_a_rope_from_its_reversal(obs_type):
    plain = straight_and_reversed(BatchedShapeControl(2, target="horizontal", obs_type=obs_type))
    marked = straight_and_reversed(BatchedShapeControl(2, target="horizontal", obs_type=obs_type, mark_end=True))
    assert torch.equal(plain["image"][0], plain["image"][1])          # the thesis's pictures cannot tell them apart
    assert not torch.equal(marked["image"][0], marked["image"][1])
    green = torch.tensor(rimage.ROPE_END_COLOR)
    for i, env_end in ((0, 0), (1, -1)):                              # the dot sits on the rope's node 0
        img = marked["image"][i].to(torch.int64)
        closest = (img - green).abs().sum(-1).flatten().argmin()
        row, col = divmod(int(closest), img.shape[1])
        node0 = rimage.world_to_pixel(torch.stack([BatchedShapeControl(1, target="horizontal").sim.target_shape(
            "horizontal")[env_end]]), 64, 1.0)[0]
        assert abs(col + 0.5 - float(node0[0])) <= 1.5 and abs(row + 0.5 - float(node0[1])) <= 1.5


def test_mark_end_must_be_a_bool():
    with pytest.raises(ValueError, match="mark_end must be True or False, got 'yes'"):
        BatchedShapeControl(1, obs_type="image", mark_end="yes")


def test_random_shift_is_a_crop_of_the_edge_padded_picture():
    torch.manual_seed(0)
    images = torch.randint(0, 256, (6, 10, 12, 3), dtype=torch.uint8)
    assert torch.equal(random_shift(images, 0), images)
    pad = 2
    shifted = random_shift(images, pad)
    assert shifted.shape == images.shape and shifted.dtype == torch.uint8
    padded = torch.nn.functional.pad(images.permute(0, 3, 1, 2).float(), (pad,) * 4, mode="replicate")
    padded = padded.permute(0, 2, 3, 1).to(torch.uint8)
    offsets = []
    for b in range(len(images)):
        hits = [(dy, dx) for dy in range(2 * pad + 1) for dx in range(2 * pad + 1)
                if torch.equal(padded[b, dy:dy + 10, dx:dx + 12], shifted[b])]
        assert hits, f"image {b} is not a crop of its padded picture"
        offsets.append(hits[0])
    assert len(set(offsets)) > 1                                      # each picture gets its own offset


def test_shift_images_moves_rope_and_target_pictures_together():
    torch.manual_seed(1)
    base = torch.randint(0, 256, (8, 16, 16, 3), dtype=torch.uint8)
    obs = {"image": base, "target_image": base.clone(), "other": torch.ones(8, 2)}
    out = shift_images(obs, 3)
    assert torch.equal(out["image"], out["target_image"])              # one offset per scene
    assert not torch.equal(out["image"], base) and out["other"] is obs["other"]
    assert shift_images(obs, 0) is obs and shift_images(torch.ones(2, 3), 3).shape == (2, 3)


def test_keypoint_encoder_finds_a_bright_spot_below_pixel_size():
    """With the convolutions replaced by the picture's red ink (1 - red/255), each keypoint is the spot's centre of
    mass: x and y in [-1, 1], rows counted from the top."""
    torch.manual_seed(0)
    enc = KeypointCNN(3, 64, (4,), keypoints=2)
    enc.conv = torch.nn.Conv2d(3, 2, 1)                               # a 1x1 conv: map = 40 * red ink
    with torch.no_grad():
        enc.conv.weight.zero_()
        enc.conv.bias.zero_()
        enc.conv.weight[:, 0] = 40.0
    h = w = 64
    enc.xs, enc.ys = torch.linspace(-1, 1, w), torch.linspace(1, -1, h)
    img = torch.full((1, h, w, 3), 255, dtype=torch.uint8)            # a white table ...
    img[0, 10, 50:52, 0] = 0                                           # ... with ink on two pixels: centre 50.5
    xy = enc(img)[0].detach()
    assert xy.shape == (4,)
    assert float(xy[0]) == pytest.approx(-1 + 2 * 50.5 / 63, abs=0.02)   # sub-pixel: between columns 50 and 51
    assert float(xy[2]) == pytest.approx(1 - 2 * 10 / 63, abs=0.02)
    out = KeypointCNN(6, 64, (8,), 5)(torch.randint(0, 256, (3, 64, 64, 6), dtype=torch.uint8))
    assert out.shape == (3, 10) and bool((out.abs() <= 1).all())


IMAGE = ["--obs", "image", "--set", "features=raw", "--set", "normalize_obs=false", "--set", "encoder=keypoints",
         "--set", "cnn_channels=[4]", "--set", "keypoints=4", "--set", "image_size=16", "--set", "augment_shift=2",
         "--set", "mark_end=true"]


@pytest.mark.parametrize("algo", ["sac", "ppo"])
def test_image_learner_with_shift_resumes_exactly(algo, tmp_path):
    """The shift draws from the seeded global generator, saved in the checkpoint: resumed = uninterrupted."""
    m = {"sac": sac, "ppo": ppo}[algo]
    a, b = tmp_path / "a", tmp_path / "b"
    extra = IMAGE + (["--set", "buffer_size=2048"] if algo == "sac" else [])
    assert m.main(argv(algo, a, 384, *extra)) == 0
    assert m.main(argv(algo, b, 256, *extra)) == 0
    assert m.main(["--out", str(b), "--resume", "--total-steps", "384", "--no-progress"]) == 0
    for name in ("train.csv", "eval.csv"):
        assert (a / name).read_text() == (b / name).read_text(), name
    assert json.loads((a / "results.json").read_text())["episodes"] == json.loads((b / "results.json").read_text())["episodes"]


def test_image_sac_trains_its_critics_encoder(tmp_path):
    """The critic's CNN learns from the critic loss: after some updates the online encoder has moved away from its
    Polyak-averaged target (an encoder left out of the update would stay equal to it)."""
    assert sac.main(argv("sac", tmp_path, 256, *IMAGE, "--set", "buffer_size=2048")) == 0
    ck = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    keys = [k for k in ck["critic"] if k.startswith("feat.enc.cnn.conv") and k.endswith("weight")]
    assert keys
    assert all(not torch.allclose(ck["critic"][k], ck["critic_target"][k]) for k in keys)


def test_image_preset_loads_and_says_why():
    cfg = load_config(ppo.PPOConfig, "params/ppo-image.yaml")
    assert (cfg.task.obs, cfg.policy, cfg.inputs.encoder, cfg.task.mark_end) == ("image", "hybrid", "keypoints", True)
    assert cfg.inputs.augment_shift > 0


@pytest.mark.parametrize("key,value,message", [("encoder", "resnet", "unknown encoder 'resnet'"),
                                               ("augment_shift", -1, "augment_shift must be a non-negative integer"),
                                               ("keypoints", 0, "keypoints must be a positive integer"),
                                               ("mark_end", "yes", "mark_end must be true or false")])
def test_bad_image_settings_are_named(key, value, message):
    with pytest.raises(ValueError, match=message):
        load_config(ppo.PPOConfig, "ppo", {key: value})


def test_keypoints_of_different_ropes_differ_at_initialization():
    """Untrained keypoints must already move with the rope: on the white table's light (x/255, temperature 1) they
    all sat at the picture's centre (std ~2e-4 over ropes) and a probe regression collapsed to the mean."""
    torch.manual_seed(0)
    env = BatchedShapeControl(32, target="random", obs_type="image", mark_end=True)
    obs, _ = env.reset(seed=0)
    enc = KeypointCNN(6, 64, (16,), 32)
    with torch.no_grad():
        xy = enc(torch.cat([obs["image"], obs["target_image"]], dim=-1))
    assert float(xy.std(0).mean()) > 0.02
