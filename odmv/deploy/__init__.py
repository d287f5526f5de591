"""A trained net outside training: a checkpoint or an exported ONNX model as a depth
function (:mod:`~odmv.deploy.inference`)."""
