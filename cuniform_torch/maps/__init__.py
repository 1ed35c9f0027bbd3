"""Map-conditioned policies (C-Free-Uniform): the local map, its encoder and local features, sensing, the policy and its checkpoint."""
