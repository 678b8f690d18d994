"""The benchmarks' anchors: FLOP counts against hand calculations, the part meter, the
learner benchmark's summary (medians, ratios, fractions of the peak), the reference loader."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest
import torch

from bench import hardware, learner, reference


def conv_flops(batch: int, c_in: int, c_out: int, k: int, out_h: int, out_w: int) -> int:
    """Two FLOPs per multiply-add; one output value takes c_in * k * k of them (bias not counted)."""
    return 2 * batch * c_out * out_h * out_w * c_in * k * k


def test_conv_layer_flops_match_a_hand_count():
    # The encoder's first layer: 9 channels in, 32 out, 3x3 stride 2 on 84x84 -> 41x41.
    conv = torch.nn.Conv2d(9, 32, 3, stride=2)
    x = torch.randn(4, 9, 84, 84)
    forward = conv_flops(4, 9, 32, 3, 41, 41)
    assert forward == 34_857_216
    assert hardware.count_flops(lambda: conv(x)) == forward
    # Backward without an input gradient: the weight gradient alone, as many FLOPs as forward.
    assert hardware.count_flops(lambda: conv(x).sum().backward()) == 2 * forward
    # With the input's gradient too: forward + grad input + grad weight.
    xg = x.clone().requires_grad_(True)
    assert hardware.count_flops(lambda: conv(xg).sum().backward()) == 3 * forward


def test_linear_layer_flops_match_a_hand_count():
    linear = torch.nn.Linear(200, 1024)
    assert hardware.count_flops(lambda: linear(torch.randn(128, 200))) == 2 * 128 * 200 * 1024


def test_every_gemm_the_peak_times_computes_the_same_product():
    gen = torch.Generator().manual_seed(0)
    a, b = torch.randn(64, 48, generator=gen), torch.randn(48, 32, generator=gen)
    calls = hardware.gemm_calls(a, b)
    assert set(calls) == {"mm", "onednn_conv1x1"}  # on a CPU: BLAS and oneDNN
    for name, product in calls.items():
        out = product()
        if out.dim() == 4:  # the 1x1 convolution's (1, n, m, 1) output
            out = out[0, :, :, 0].t()
        torch.testing.assert_close(out, a @ b, msg=name)


def test_matmul_peak_is_a_positive_rate():
    peak = hardware.matmul_peak_gflops(torch.device("cpu"), sizes=(128,), seconds=0.05)
    assert peak > 0.0


def test_machine_names_the_cpu_and_threads():
    info = hardware.machine(torch.device("cpu"))
    assert info["cpu_model"] and info["torch_threads"] == torch.get_num_threads()


class Toy:
    def __init__(self) -> None:
        self.a = torch.nn.Linear(8, 16)
        self.b = torch.nn.Linear(16, 4)

    def first(self, x):
        return self.a(x)

    def second(self, h):
        return self.b(h)

    def both(self, x):
        return self.second(self.first(x))


def test_part_meter_counts_each_part_and_restores_the_methods():
    toy = Toy()
    x = torch.randn(10, 8)
    meter = hardware.PartMeter(
        toy, {"a": ("first",), "b": ("second",), "missing": ("no_such_method",)}, torch.device("cpu")
    )
    assert set(meter.parts) == {"a", "b"}
    with meter.attached(count=True):
        toy.both(x)
        toy.both(x)
    assert meter.flops == {"a": 2 * (2 * 10 * 8 * 16), "b": 2 * (2 * 10 * 16 * 4)}
    assert meter.seconds["a"] > 0 and meter.seconds["b"] > 0
    assert "first" not in vars(toy) and toy.first.__func__ is Toy.first


def test_part_meter_counts_a_nested_call_once_in_the_outer_part():
    toy = Toy()
    meter = hardware.PartMeter(toy, {"outer": ("both",), "inner": ("first",)}, torch.device("cpu"))
    with meter.attached(count=True):
        toy.both(torch.randn(10, 8))
    assert meter.flops["inner"] == 0
    assert meter.flops["outer"] == 2 * 10 * 8 * 16 + 2 * 10 * 16 * 4


def project_result(rate: float, count: bool) -> dict:
    result = {
        "updates_per_s": rate,
        "part_seconds_per_update": {"critic": 0.5, "actor": 0.1},
        "score_ms_per_transition": {"stored_order": 2.0, "batch_1": 10.0},
        "variant_updates_per_s": {"pixel_td3": 3 * rate, "nasa_td3+bf16": 2 * rate},
        "variant_score_ms_stored_order": {"nasa_td3+bf16": 1.25},
        "load_avg_1m": 0.0,
    }
    if count:
        result |= {
            "update_flops": 100e9,
            "part_flops_per_update": {"critic": 50e9, "actor": 1e9},
            "score_flops_per_transition": {"stored_order": 0.2e9, "batch_1": 0.3e9},
        }
    return result


def rounds(with_reference: bool) -> list[dict]:
    out = []
    for i, (rate, ref_rate, peak) in enumerate([(1.0, 0.4, 200.0), (0.5, 0.2, 100.0), (0.8, 0.5, 250.0)]):
        r = {"project": project_result(rate, count=i == 0), "peak": {"fp32": peak}}
        if with_reference:
            r["reference"] = {"updates_per_s": ref_rate, "score_ms_per_transition": {"batch_1": 25.0}}
            if i == 0:
                r["reference"] |= {"update_flops": 150e9, "score_flops_per_transition": {"batch_1": 0.5e9}}
        out.append(r)
    return out


def test_summary_takes_medians_and_ratios_to_the_reference():
    s = learner.summarize(rounds(with_reference=True), "cpu", 128)
    assert s["updates_per_s"] == 0.8 and s["reference_updates_per_s"] == 0.4
    assert s["update_ratio"] == 2.0
    assert s["score_ratio_stored_order"] == 12.5 and s["score_ratio_batch_1"] == 2.5
    assert s["sgemm_peak_gflops"] == 200.0
    # 100 GFLOP per update at 0.8 updates/s over 200 GFLOP/s.
    assert s["update_fraction_of_peak"] == 0.4
    assert s["part_fraction_of_peak"] == {"critic": 0.5, "actor": 0.05}
    assert s["score_fraction_of_peak"] == {"stored_order": 0.5, "batch_1": 0.15}
    assert s["score_gflop_per_transition"] == {"stored_order": 0.2, "batch_1": 0.3}
    assert s["reference_update_fraction_of_peak"] == 0.3
    assert s["goals_met"] == {
        "update_ratio": False,
        "update_fraction_of_peak": False,
        "score_ratio_stored_order": False,
    }
    assert s["per_round"]["reference_updates_per_s"] == [0.4, 0.2, 0.5]
    assert s["variant_updates_per_s"] == {"pixel_td3": 2.4, "nasa_td3+bf16": 1.6}
    assert s["variant_update_ratio"] == {"pixel_td3": 6.0, "nasa_td3+bf16": 4.0}
    # Only a variant with intrinsic rewards scores: 25 ms against 1.25 ms per transition.
    assert s["variant_score_ms_stored_order"] == {"nasa_td3+bf16": 1.25}
    assert s["variant_score_ratio_stored_order"] == {"nasa_td3+bf16": 20.0}


def test_summary_reports_a_cpu_bf16_peak_beside_the_fp32_one():
    both = rounds(with_reference=False)
    for r, bf16 in zip(both, (800.0, 400.0, 1000.0), strict=True):
        r["peak"] |= {"bf16": bf16, "torch_threads": 2, "load_avg_1m": 0.5}
    s = learner.summarize(both, "cpu", 128)
    assert s["matmul_peak_gflops"] == {"fp32": 200.0, "bf16": 800.0}
    assert s["update_fraction_of_peak"] == 0.4 and s["update_fraction_of_bf16_peak"] == 0.1
    assert "update_fraction_of_tf32_peak" not in s
    assert "matmul_peak_gflops" not in learner.summarize(rounds(with_reference=False), "cpu", 128)


def test_summary_warns_when_the_machine_was_busy():
    busy = rounds(with_reference=True)
    busy[1]["project"]["load_avg_1m"] = 4.0 * (os.cpu_count() or 1)
    assert "busy machine" in learner.summarize(busy, "cpu", 128)["warning"]
    assert "warning" not in learner.summarize(rounds(with_reference=True), "cpu", 128)


def test_summary_without_the_reference_has_no_ratio():
    s = learner.summarize(rounds(with_reference=False), "cpu", 128)
    assert "update_ratio" not in s and "reference_updates_per_s" not in s
    assert s["goals_met"]["update_ratio"] is None
    assert s["update_fraction_of_peak"] == 0.4


def test_worker_commands_alternate_and_count_once():
    args = learner.parse_args(["--reference", "/ref", "--rounds", "3"])
    cmd = learner.worker_command(args, "reference", Path("/tmp/b.npz"), count=True)
    assert cmd[cmd.index("--worker") + 1] == "reference" and "--count-flops" in cmd
    assert cmd[cmd.index("--reference") + 1] == "/ref"
    assert "--count-flops" not in learner.worker_command(args, "project", Path("/tmp/b.npz"), count=False)
    args = learner.parse_args(["--variants", "all"])
    assert args.variants == list(learner.VARIANTS)
    project = learner.worker_command(args, "project", Path("/tmp/b.npz"), count=False)
    assert project[project.index("--variants") + 1] == ",".join(learner.VARIANTS)
    # the peak worker reads them for whether to time the bf16 peak; the reference's never runs them
    assert "--variants" in learner.worker_command(args, "peak", Path("/tmp/b.npz"), count=False)
    assert "--variants" not in learner.worker_command(args, "reference", Path("/tmp/b.npz"), count=False)
    with pytest.raises(SystemExit):
        learner.parse_args(["--variants", "td3_ae,no_such_agent"])


def test_reference_loader_rejects_a_directory_that_is_not_a_checkout(tmp_path):
    with pytest.raises(reference.ReferenceError, match="not a checkout"):
        reference.load_class(tmp_path)


def test_reference_loader_imports_the_agent_from_the_checkout(tmp_path):
    (tmp_path / "networks").mkdir()
    (tmp_path / "networks" / "__init__.py").write_text("WIDTH = 3\n")
    (tmp_path / "nasa_td3.py").write_text(
        textwrap.dedent("""
        from networks import WIDTH

        class AE_TD3:
            def __init__(self, latent_size, action_num, device, k):
                self.shape = (latent_size, action_num, k * WIDTH)
    """)
    )
    agent = reference.make(tmp_path, 6, 3, torch.device("cpu"))
    assert agent.shape == (reference.LATENT_SIZE, 6, 9)
    assert str(tmp_path) not in [str(Path(p).resolve()) for p in __import__("sys").path]


def test_sac_ae_reference_loader_names_the_files_a_checkout_lacks(tmp_path):
    (tmp_path / "sac_ae.py").write_text("")
    with pytest.raises(reference.ReferenceError, match="no encoder.py, decoder.py, utils.py"):
        reference.load_sac_ae(tmp_path)


def test_sac_ae_reference_loader_imports_the_module_and_leaves_its_common_names_free(tmp_path):
    import sys

    for name, text in {"encoder.py": "WIDTH = 3\n", "decoder.py": "from encoder import WIDTH\n",
                       "utils.py": "", "sac_ae.py": "import utils\nfrom decoder import WIDTH\n"
                                                   "class SacAeAgent:\n    width = WIDTH\n"}.items():
        (tmp_path / name).write_text(text)
    module = reference.load_sac_ae(tmp_path)
    assert module.SacAeAgent.width == 3
    assert not {"sac_ae", "encoder", "decoder", "utils"} & set(sys.modules)
    assert str(tmp_path) not in [str(Path(p).resolve()) for p in sys.path]


@pytest.mark.skipif(not os.environ.get("NASA_REFERENCE_DIR"), reason="set NASA_REFERENCE_DIR to a checkout")
def test_the_real_reference_scores_one_transition():
    import numpy as np

    agent = reference.make(Path(os.environ["NASA_REFERENCE_DIR"]), 6, 3, torch.device("cpu"))
    rng = np.random.default_rng(0)
    obs = rng.integers(0, 256, (9, 84, 84), dtype=np.uint8)
    value = reference.score_one(agent, obs, rng.uniform(-1, 1, 6).astype(np.float32), obs)
    assert np.isfinite(value) and value > 0
