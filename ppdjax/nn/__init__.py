"""The PPD network (Flax NNX): encoders, the recurrent primitive generator, the loss."""
