"""A popcode ONNX model's weights read back into the trainer's network.

The shipped models keep no training checkpoint, only their ONNX files, so a refresh that fine-tunes them (issue 51:
a share of path-traced crops) starts from the weights in those files. The exporter folds each BatchNorm into the
convolution before it and may store weights in fp16, as int8 with a scale, or as 8-bit blocks (``MatMulNBits``);
:func:`read_back` undoes each of those. A folded BatchNorm cannot be split again from its convolution alone, but
any split works in eval mode, and one split also keeps training mode's output: the BatchNorm whose statistics are
those of the convolution's output on real crops. :func:`read_back` therefore fits each BatchNorm to ``crops``
(the runtime's crops of the data the fine-tuning will see), layer by layer, so that the network's first batches
in training compute what the file computes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import torch
from google.protobuf.message import DecodeError
from onnx import numpy_helper
from torch import nn

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.model.metadata import ModelMetadata

from ..train.network import NetworkConfig, OutputLayer, PopcodeNet, build_network

DENSE_OPS = ("Gemm", "MatMul", "MatMulNBits")


class _Weights:
    """The float value of any tensor of a graph that is a constant: an initializer, or one read through ``Cast``
    (fp16), ``DequantizeLinear`` (int8 with scales) or ``Identity``."""

    def __init__(self, graph: onnx.GraphProto) -> None:
        self.initializers = {init.name: init for init in graph.initializer}
        self.producers = {output: node for node in graph.node for output in node.output}

    def value(self, name: str) -> np.ndarray:
        if name in self.initializers:
            return numpy_helper.to_array(self.initializers[name]).astype(np.float32)
        node = self.producers.get(name)
        if node is None:
            raise PopcodeError(f"tensor {name!r} is not a constant of the graph")
        if node.op_type in ("Cast", "Identity"):
            return self.value(node.input[0])
        if node.op_type == "DequantizeLinear":
            return self._dequantised(node)
        raise PopcodeError(f"tensor {name!r} is computed by a {node.op_type} node, not read from weights")

    def _dequantised(self, node: onnx.NodeProto) -> np.ndarray:
        values = self.value(node.input[0])
        scale = self.value(node.input[1])
        zero = self.value(node.input[2]) if len(node.input) > 2 and node.input[2] else np.zeros_like(scale)
        if scale.ndim == 1 and scale.size > 1:  # per channel, along ``axis``
            axis = next((a.i for a in node.attribute if a.name == "axis"), 1) % values.ndim
            shape = [1] * values.ndim
            shape[axis] = scale.size
            scale, zero = scale.reshape(shape), zero.reshape(shape)
        return (values - zero) * scale

    def matmul_nbits(self, node: onnx.NodeProto) -> np.ndarray:
        """The ``(K, N)`` float weight of an 8-bit ``MatMulNBits`` node without zero points."""
        attributes = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        if attributes.get("bits") != 8 or len(node.input) > 3 and node.input[3]:
            raise PopcodeError(f"{node.name}: only 8-bit MatMulNBits without zero points is read back")
        rows, columns = attributes["K"], attributes["N"]
        packed = self.value(node.input[1])  # (N, blocks, block) of unsigned bytes, 128 the zero
        scales = self.value(node.input[2]).reshape(columns, -1, 1)
        return ((packed - 128.0) * scales).reshape(columns, -1)[:, :rows].T


def _execution_order(model: nn.Module, input_size: int) -> tuple[list[nn.Conv2d], dict[nn.Conv2d, nn.BatchNorm2d],
                                                                 list[nn.Module]]:
    """The convolutions and dense layers of ``model`` in the order a forward pass runs them (the order the exported
    graph holds them in), and the BatchNorm that follows each convolution (folded into it at export)."""
    convs: list[nn.Conv2d] = []
    dense: list[nn.Module] = []
    folded: dict[nn.Conv2d, nn.BatchNorm2d] = {}
    outputs: dict[int, nn.Conv2d] = {}

    def record(module: nn.Module, inputs: tuple, output: torch.Tensor) -> None:
        if isinstance(module, nn.Conv2d):
            convs.append(module)
            outputs[id(output)] = module
        elif isinstance(module, nn.BatchNorm2d):
            folded[outputs[id(inputs[0])]] = module
        else:
            dense.append(module)

    hooks = [m.register_forward_hook(record) for m in model.modules()
             if isinstance(m, nn.Conv2d | nn.BatchNorm2d | nn.Linear | OutputLayer)]
    try:
        with torch.no_grad():
            model.eval()(torch.zeros(2, 1, input_size, input_size))
    finally:
        for hook in hooks:
            hook.remove()
    return convs, folded, dense


def _consumers(graph: onnx.GraphProto) -> dict[str, list[onnx.NodeProto]]:
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    return consumers


def _dense_weights(weights: _Weights, graph: onnx.GraphProto) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each dense layer's ``(in, out)`` weight and bias: the hidden layers in graph order, then the output layer's
    column blocks (one ``MatMul`` + ``Add`` each) in the order its ``Concat`` joins them."""
    consumers = _consumers(graph)
    layers: list[tuple[str, np.ndarray, np.ndarray]] = []  # (the tensor holding its output, weight, bias)
    for node in (n for n in graph.node if n.op_type in DENSE_OPS):
        if node.op_type == "Gemm":
            attributes = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
            weight = weights.value(node.input[1])
            layers.append((node.output[0], weight.T if attributes.get("transB", 0) else weight,
                           weights.value(node.input[2])))
            continue
        weight = weights.matmul_nbits(node) if node.op_type == "MatMulNBits" else weights.value(node.input[1])
        add = next((n for n in consumers.get(node.output[0], []) if n.op_type == "Add"), None)
        if add is None:
            raise PopcodeError(f"{node.name}: a dense layer without a bias, which popcode's exporter never writes")
        bias_name = next(name for name in add.input if name != node.output[0])
        layers.append((add.output[0], weight, weights.value(bias_name)))
    joined = next((n for n in graph.node if n.op_type == "Concat" and
                   {name for name, _, _ in layers} >= set(n.input)), None)
    if joined is not None:  # the output layer in column blocks: put them in the Concat's order
        blocks = {name: (weight, bias) for name, weight, bias in layers if name in joined.input}
        rest = [(weight, bias) for name, weight, bias in layers if name not in blocks]
        return rest + [blocks[name] for name in joined.input]
    return [(weight, bias) for _, weight, bias in layers]


def _module_name(node_name: str) -> str:
    """The module an exported node belongs to, from its scope: ``/features/features.3/body/body.0/Conv`` ->
    ``features.3.body.0`` (each scope repeats its parent's name before adding its own)."""
    scopes = [scope for scope in node_name.strip("/").split("/")[:-1] if scope]
    kept = [scope for scope, child in zip(scopes, [*scopes[1:], ""], strict=True)
            if not child.startswith(scope + ".")]
    return ".".join(kept)


def _fit_batch_norm(model: nn.Module, conv: nn.Conv2d, norm: nn.BatchNorm2d, bias: torch.Tensor,
                    crops: torch.Tensor) -> None:
    """Give ``norm`` the statistics of ``conv``'s output on ``crops`` and the scale and shift that make
    ``norm(conv(x))`` equal the folded ``conv(x) + bias``, in eval mode and in training mode on such crops."""
    captured: list[torch.Tensor] = []
    hook = conv.register_forward_hook(lambda _m, _i, output: captured.append(output.detach()))
    try:
        with torch.no_grad():
            model.eval()(crops)
    finally:
        hook.remove()
    output = captured[0]
    mean = output.mean(dim=(0, 2, 3))
    variance = output.var(dim=(0, 2, 3), unbiased=False)
    with torch.no_grad():
        norm.running_mean.copy_(mean)
        norm.running_var.copy_(variance)
        norm.weight.copy_((variance + norm.eps).sqrt())
        norm.bias.copy_(bias + mean)


def read_back(path: str | Path, crops: np.ndarray) -> tuple[PopcodeNet, ModelMetadata]:
    """The network (eval mode) an exported popcode model at ``path`` computes, and its metadata; ``crops``
    ``(N, 1, S, S)`` fit the BatchNorms (a few hundred of the training data's crops: see the module's docstring).

    PopcodeError in one line for a file that is not a popcode pose model exported by this trainer, or whose
    graph does not hold the weights its training config describes."""
    try:
        graph_model = onnx.load(str(path))
    except (OSError, DecodeError) as error:
        raise PopcodeError(f"{path}: not a readable ONNX model ({error})") from error
    metadata = ModelMetadata.from_props({prop.key: prop.value for prop in graph_model.metadata_props})
    config = (metadata.training or {}).get("config", {}).get("network")
    if not isinstance(config, dict):
        raise PopcodeError(f"{path}: its metadata has no training config, so its network cannot be rebuilt")
    weights = _Weights(graph_model.graph)
    layers = _dense_weights(weights, graph_model.graph)
    fields = {key: tuple(value) if isinstance(value, list) else value for key, value in config.items()}
    output_layers = layers[len(fields.get("hidden", ())):]  # the output layer's column blocks
    fields.update(input_size=metadata.input_size, output_dim=sum(bias.size for _, bias in output_layers))
    model = build_network(NetworkConfig(**fields))
    convs, folded, dense = _execution_order(model, metadata.input_size)
    conv_nodes = _conv_nodes(graph_model.graph, model, convs)
    if len(conv_nodes) != len(convs) or len(layers) < len(dense):
        raise PopcodeError(f"{path}: its graph holds {len(conv_nodes)} convolutions and {len(layers)} dense layers, "
                           f"its network {len(convs)} and {len(dense)}: not a model of this trainer")
    biases: dict[nn.Conv2d, torch.Tensor] = {}
    for conv, node in zip(convs, conv_nodes, strict=True):
        weight = torch.from_numpy(weights.value(node.input[1]))
        bias = torch.from_numpy(weights.value(node.input[2])) if len(node.input) > 2 else torch.zeros(len(weight))
        _check_shape(path, node.name, weight.shape, conv.weight.shape)
        with torch.no_grad():
            conv.weight.copy_(weight)
            if conv in folded:
                biases[conv] = bias
            elif conv.bias is not None:
                conv.bias.copy_(bias)
    _load_dense(path, dense, layers)
    batch = torch.as_tensor(np.asarray(crops, np.float32))
    for conv in convs:  # in order: each BatchNorm's input is computed by the ones fitted before it
        if conv in folded:
            _fit_batch_norm(model, conv, folded[conv], biases[conv], batch)
    return model.eval(), metadata


def _conv_nodes(graph: onnx.GraphProto, model: nn.Module, convs: list[nn.Conv2d]) -> list[onnx.NodeProto]:
    """The graph's convolutions in the order of ``convs`` (a forward pass's): by the module each node's scope
    names (a quantised graph need not keep the export's order), else in graph order."""
    nodes = [node for node in graph.node if node.op_type == "Conv"]
    position = {id(conv): index for index, conv in enumerate(convs)}
    order = {name: position[id(module)] for name, module in model.named_modules() if id(module) in position}
    if all(_module_name(node.name) in order for node in nodes):
        return sorted(nodes, key=lambda node: order[_module_name(node.name)])
    return nodes


def _load_dense(path: str | Path, modules: list[nn.Module], layers: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """The hidden layers one node each, then the output layer from the remaining nodes' column blocks."""
    hidden, output = modules[:-1], modules[-1]
    for module, (weight, bias) in zip(hidden, layers, strict=False):
        _assign(path, module, weight, bias)
    rest = layers[len(hidden):]
    _assign(path, output, np.concatenate([w for w, _ in rest], axis=1), np.concatenate([b for _, b in rest]))


def _assign(path: str | Path, module: nn.Module, weight: np.ndarray, bias: np.ndarray) -> None:
    """Copy an ``(in, out)`` weight and its bias into a Linear (which stores ``(out, in)``) or an OutputLayer."""
    value = torch.from_numpy(np.ascontiguousarray(weight.T if isinstance(module, nn.Linear) else weight))
    _check_shape(path, type(module).__name__, value.shape, module.weight.shape)
    _check_shape(path, f"{type(module).__name__} bias", bias.shape, module.bias.shape)
    with torch.no_grad():
        module.weight.copy_(value)
        module.bias.copy_(torch.from_numpy(bias))


def _check_shape(path: str | Path, what: str, found: tuple | torch.Size, expected: torch.Size) -> None:
    if tuple(found) != tuple(expected):
        raise PopcodeError(f"{path}: {what} holds a weight of shape {tuple(found)} where its network has "
                           f"{tuple(expected)}: not a model of this trainer")

