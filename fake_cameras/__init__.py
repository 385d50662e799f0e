"""A simulated capture rig that renders real images of animated synthetic creatures, with ground truth."""
