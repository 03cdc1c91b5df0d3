"""Tools around the method: the scene simulator, the benchmarks, the oracles and the demo. The method never imports them."""
