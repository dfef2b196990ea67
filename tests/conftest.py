import pytest
import torch

# Tests check correctness, not speed: one torch thread per process avoids oversubscribing the two cores
# that the two pytest-xdist workers already share.
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
