"""The map model: HD maps, SD maps, lane graphs (the interchange format), lane neighbours and the road graph of
an SD map."""
