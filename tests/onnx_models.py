"""Tiny ONNX networks with the interfaces of the learned priors' real ones (not their weights),
built by the tests themselves."""

import numpy as np
import onnx
from onnx import TensorProto, helper

IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


def save_model(path, nodes, outputs, initializers, input_shape=(1, 3, "height", "width")):
    graph = helper.make_graph(
        nodes,
        "tiny",
        [helper.make_tensor_value_info("pixel_values", TensorProto.FLOAT, list(input_shape))],
        outputs,
        initializers,
    )
    # IR version 8 (opset 17): what every ONNX Runtime since 1.14 reads, whatever onnx writes by default.
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def constant(name, values):
    values = np.asarray(values, np.float32 if np.asarray(values).dtype.kind == "f" else np.int64)
    kind = TensorProto.FLOAT if values.dtype == np.float32 else TensorProto.INT64
    return helper.make_tensor(name, kind, values.shape, values.ravel().tolist())


def affine_red_model(path, a, b, input_shape=(1, 3, "height", "width")):
    """out = a * input[:, 0] + b as a (1, 1, h, w) "predicted_depth"; a (1, 3) first output that
    is no image, so that the provider must pick the right one."""
    nodes = [
        helper.make_node("Slice", ["pixel_values", "start", "end", "axis"], ["red"]),
        helper.make_node("Mul", ["red", "a"], ["scaled"]),
        helper.make_node("Add", ["scaled", "b"], ["predicted_depth"]),
        helper.make_node("ReduceMean", ["pixel_values"], ["colour"], axes=[2, 3], keepdims=0),
    ]
    outputs = [
        helper.make_tensor_value_info("colour", TensorProto.FLOAT, [1, 3]),
        helper.make_tensor_value_info(
            "predicted_depth", TensorProto.FLOAT, [1, 1, "height", "width"]
        ),
    ]
    inits = [
        constant("start", [0]),
        constant("end", [1]),
        constant("axis", [1]),
        constant("a", [a]),
        constant("b", [b]),
    ]
    return save_model(path, nodes, outputs, inits, input_shape)


def row_ramp_model(path, height, width, top, bottom):
    """A relative depth for inputs of ``height`` x ``width``: ``top`` on the first row down to
    ``bottom`` on the last, whatever the image (as a room seen from inside: far at the top, the
    floor near at the bottom), as "predicted_depth" (1, 1, h, w)."""
    ramp = np.repeat(np.linspace(top, bottom, height, dtype=np.float32)[:, None], width, axis=1)
    nodes = [
        helper.make_node("ReduceMean", ["pixel_values"], ["grey"], axes=[1], keepdims=1),
        helper.make_node("Mul", ["grey", "zero"], ["zeros"]),
        helper.make_node("Add", ["zeros", "ramp"], ["predicted_depth"]),
    ]
    outputs = [
        helper.make_tensor_value_info("predicted_depth", TensorProto.FLOAT, [1, 1, height, width])
    ]
    inits = [
        constant("zero", [0.0]),
        helper.make_tensor("ramp", TensorProto.FLOAT, [1, 1, height, width], ramp.ravel().tolist()),
    ]
    return save_model(path, nodes, outputs, inits, (1, 3, height, width))


def constant_normal_model(path, normal):
    """A depth output, then "predicted_normal" (1, 4, h, w): ``normal`` and a confidence everywhere."""
    nodes = [
        helper.make_node("ReduceMean", ["pixel_values"], ["grey"], axes=[1], keepdims=1),
        helper.make_node("Mul", ["grey", "zero"], ["zeros"]),
        helper.make_node("Add", ["zeros", "one"], ["predicted_depth"]),
        helper.make_node("Add", ["zeros", "normal"], ["predicted_normal"]),
    ]
    outputs = [
        helper.make_tensor_value_info(
            "predicted_depth", TensorProto.FLOAT, [1, 1, "height", "width"]
        ),
        helper.make_tensor_value_info(
            "predicted_normal", TensorProto.FLOAT, [1, 4, "height", "width"]
        ),
    ]
    inits = [
        constant("zero", [0.0]),
        constant("one", [1.0]),
        helper.make_tensor("normal", TensorProto.FLOAT, [1, 4, 1, 1], [*normal, 0.9]),
    ]
    return save_model(path, nodes, outputs, inits)


def nan_model(path, channels=1):
    """NaN everywhere: one channel ("predicted_depth"), or with ``channels`` 3 one per input
    channel ("scores", as a segmenter's per-class scores)."""
    nodes = [
        helper.make_node("Sub", ["pixel_values", "pixel_values"], ["zeros"]),
        helper.make_node("Div", ["zeros", "zeros"], ["scores" if channels == 3 else "nan"]),
    ]
    name = "predicted_depth"
    if channels == 1:
        nodes.append(helper.make_node("ReduceMean", ["nan"], [name], axes=[1], keepdims=1))
    else:
        name = "scores"
    outputs = [
        helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, channels, "height", "width"])
    ]
    return save_model(path, nodes, outputs, [])


def highlight_model(path):
    """A pixelwise stand-in of a SHIQ-family network, its outputs in JSHDR's order: "mask" (1, 1,
    h, w) the mean of the RGB input, "residue" (1, 3, h, w) zeros, "diffuse" (1, 3, h, w) half the
    input."""
    nodes = [
        helper.make_node("ReduceMean", ["pixel_values"], ["mask"], axes=[1], keepdims=1),
        helper.make_node("Mul", ["pixel_values", "zero"], ["residue"]),
        helper.make_node("Mul", ["pixel_values", "half"], ["diffuse"]),
    ]
    outputs = [
        helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, c, "height", "width"])
        for name, c in (("mask", 1), ("residue", 3), ("diffuse", 3))
    ]
    return save_model(path, nodes, outputs, [constant("zero", [0.0]), constant("half", [0.5])])


def brightness_segmentation_model(path, threshold, scores=False):
    """A two-class segmenter: class 1 where the mean of the RGB input exceeds ``threshold`` (bright
    sky), else 0. As labels, a (1, 1, h, w) "labels" output; with ``scores``, per-class scores
    (1, 2, h, w) "logits" (threshold - grey, grey - threshold) behind a first output that is no
    class map."""
    nodes = [helper.make_node("ReduceMean", ["pixel_values"], ["grey"], axes=[1], keepdims=1)]
    if scores:
        nodes += [
            helper.make_node("Sub", ["threshold", "grey"], ["below"]),
            helper.make_node("Sub", ["grey", "threshold"], ["above"]),
            helper.make_node("Concat", ["below", "above"], ["logits"], axis=1),
            helper.make_node("ReduceMean", ["pixel_values"], ["colour"], axes=[2, 3], keepdims=0),
        ]
        outputs = [
            helper.make_tensor_value_info("colour", TensorProto.FLOAT, [1, 3]),
            helper.make_tensor_value_info("logits", TensorProto.FLOAT, [1, 2, "height", "width"]),
        ]
    else:
        nodes += [
            helper.make_node("Greater", ["grey", "threshold"], ["bright"]),
            helper.make_node("Cast", ["bright"], ["labels"], to=TensorProto.INT64),
        ]
        outputs = [
            helper.make_tensor_value_info("labels", TensorProto.INT64, [1, 1, "height", "width"])
        ]
    return save_model(path, nodes, outputs, [constant("threshold", [float(threshold)])])
