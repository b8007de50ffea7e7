"""Drake LeafSystems and the vectorized numerical cores they wrap.

Each core module is plain numpy/scipy and works on batches; the LeafSystem beside it is a thin
adapter (ports in, call the core, ports out).
"""
