"""The model: PoseNet's head, the loss, training (one process or torchrun),
checkpoints, model files and the ONNX export. Builds on relocfw.core only."""
