//! Global descriptors from the network's feature map, their distance and the score derived from it.
