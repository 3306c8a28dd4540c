"""Policies outside Python and JAX: a run's actor as an ONNX graph (``eabc export-policy``).

The graph is the whole deterministic policy from raw observations to actions, the observation
normaliser included: ``(s - mean) / std``, the actor's ReLU layers, ``max_action * tanh(out)``.
For a Gaussian actor (CQL, SAC-N, EDAC, ...) ``out`` is the mean, the first half of the
outputs, as in :func:`eabc.networks.numpy_actor`. Built with the ``onnx`` package's helper API
from the checkpoint's arrays (plain MLPs need nothing more), so any ONNX runtime can run it:

    session = onnxruntime.InferenceSession("policy.onnx")
    action = session.run(None, {"observation": obs[None].astype(np.float32)})[0][0]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eabc import pytree
from eabc.training import checkpoint
from eabc.training.directory import read_checkpoint

OPSET = 17
PRODUCER_MARK = b"\x12\x04eabc"
"""How an ONNX file this package wrote begins: its producer_name field (protobuf field 2, 4 bytes,
"eabc") within its first bytes, after the IR version. ``eabc export-policy`` overwrites a file in
the run directory only when it bears this mark."""
"""ONNX operator set: every op used (Sub, Div, MatMul, Add, Relu, Tanh, Mul) is older than this."""


def export_onnx(run_dir: str | Path, path: str | Path) -> Path:
    """Write the policy of the latest checkpoint in ``run_dir`` to ``path`` as ONNX.

    Input ``observation`` (float32, ``[batch, obs_dim]``), output ``action`` (float32,
    ``[batch, act_dim]``).
    """
    try:
        import onnx  # noqa: PLC0415
        from onnx import TensorProto, helper, numpy_helper  # noqa: PLC0415
    except ImportError:
        raise RuntimeError(
            "exporting to ONNX needs the onnx package: pip install 'eabc[onnx]'"
        ) from None

    run_dir = Path(run_dir)
    config, algorithm, raw = read_checkpoint(run_dir)  # this run's own, of its layout and shapes
    actor = {k: np.asarray(v, np.float32) for k, v in pytree.find(raw["agent"], "actor").items()}
    if any(name.startswith("g") for name in actor):
        raise ValueError(f"{run_dir}: the actor has LayerNorm layers, which the export lacks")
    layers = sum(1 for name in actor if name.startswith("w"))
    weights = [(actor[f"w{i}"], actor[f"b{i}"]) for i in range(layers)]
    if algorithm.gaussian_actor:  # the mean: first half of outputs
        w, b = weights[-1]
        half = w.shape[1] // 2
        weights[-1] = (w[:, :half], b[:half])
    mean = np.asarray(raw["normalizer"]["mean"], np.float32)
    std = np.asarray(raw["normalizer"]["std"], np.float32)
    max_action = np.asarray(config["max_action"], np.float32)

    constants = {"obs_mean": mean, "obs_std": std, "max_action": max_action}
    nodes = [
        helper.make_node("Sub", ["observation", "obs_mean"], ["centred"]),
        helper.make_node("Div", ["centred", "obs_std"], ["h_in"]),
    ]
    h = "h_in"
    for i, (w, b) in enumerate(weights):
        constants |= {f"w{i}": w, f"b{i}": b}
        nodes += [
            helper.make_node("MatMul", [h, f"w{i}"], [f"z{i}_product"]),
            helper.make_node("Add", [f"z{i}_product", f"b{i}"], [f"z{i}"]),
        ]
        h = f"z{i}"
        if i < len(weights) - 1:
            nodes.append(helper.make_node("Relu", [h], [f"h{i}"]))
            h = f"h{i}"
    nodes += [
        helper.make_node("Tanh", [h], ["squashed"]),
        helper.make_node("Mul", ["squashed", "max_action"], ["action"]),
    ]
    obs_dim, act_dim = weights[0][0].shape[0], weights[-1][0].shape[1]
    graph = helper.make_graph(
        nodes,
        f"eabc {config['train']['algo']} policy",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", obs_dim])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", act_dim])],
        initializer=[numpy_helper.from_array(v, name) for name, v in constants.items()],
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="eabc"
    )
    model.doc_string = (
        f"{config['train']['algo']} on {config.get('dataset', {}).get('name', '?')}: raw "
        "observation -> action, observation normaliser inside"
    )
    onnx.checker.check_model(model)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    checkpoint.atomic_write(path, model.SerializeToString())
    return path
