//! Image -> network input tensor: resize to the network's input size and scale RGB to [-1, 1].
