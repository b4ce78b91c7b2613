"""Bad input to the classic engine gets a clear one-line ValueError."""

import math

import pytest
import torch

from torchseq.seqslam import SeqSLAM, SeqSLAMConfig, difference_matrix, enhance_contrast, search


def desc(n, dim=16, seed=0):
    return torch.randint(119, 136, (n, dim), generator=torch.Generator().manual_seed(seed)).float()


@pytest.mark.parametrize("ref,query,message", [
    (desc(30), desc(5), "at least ds \\+ 1 = 11 query frames"),
    (desc(1), desc(30), "at least 2 reference frames"),
    (desc(30), desc(30, dim=8), "query descriptors must have shape"),
    (desc(0), desc(30), "empty"),
    (desc(30), desc(0), "empty"),
    (desc(30, 16).reshape(30, 4, 4), desc(30), "reference descriptors must have shape"),
])
def test_match_descriptors_errors(ref, query, message):
    with pytest.raises(ValueError, match=message):
        SeqSLAM().match_descriptors(ref, query)


def test_nan_inputs_are_rejected():
    ref = desc(30)
    ref[3, 2] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        SeqSLAM().match_descriptors(ref, desc(30))
    frames = torch.rand(20, 32, 64) * 255
    frames[4, 0, 0] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        SeqSLAM().match(frames, torch.rand(20, 32, 64))
    with pytest.raises(ValueError, match="NaN"):
        difference_matrix(ref, desc(5))
    with pytest.raises(ValueError, match="NaN"):
        enhance_contrast(torch.full((4, 4), math.nan))


def test_match_frames_errors():
    with pytest.raises(ValueError, match="empty"):
        SeqSLAM().match(torch.zeros(0, 32, 64), torch.zeros(20, 32, 64))
    with pytest.raises(ValueError, match="query frames"):
        SeqSLAM().match(torch.rand(20, 32, 64), torch.rand(8, 32, 64))


def test_functional_errors():
    with pytest.raises(ValueError, match="metric"):
        difference_matrix(desc(3), desc(3), "manhattan")
    with pytest.raises(ValueError, match="window"):
        enhance_contrast(torch.rand(5, 5), 1)
    with pytest.raises(ValueError, match="query frames"):
        search(torch.rand(20, 6), 10, [1.0])
    with pytest.raises(ValueError, match="speeds"):
        search(torch.rand(20, 16), 10, [])
    with pytest.raises(ValueError, match="ds"):
        SeqSLAM(SeqSLAMConfig(ds=0))


def test_ds_odd_rounds_up_and_needs_more_queries():
    engine = SeqSLAM(SeqSLAMConfig(ds=9))
    with pytest.raises(ValueError, match="11 query frames"):
        engine.match_descriptors(desc(30), desc(10))
    out = engine.match_descriptors(desc(30), desc(11))
    assert (out.matches.reference >= 0).sum() <= 1 and out.matches.reference[0] == -1


def test_a_config_that_is_not_a_seqslamconfig_is_named():
    # StreamingSeqSLAM(config, reference) (arguments swapped) used to end in torch's
    # "Boolean value of Tensor with more than one value is ambiguous"
    from torchseq.seqslam import StreamingSeqSLAM

    frames = torch.rand(20, 32, 64)
    with pytest.raises(TypeError, match="config must be a SeqSLAMConfig or None, got Tensor"):
        SeqSLAM(frames)
    with pytest.raises(TypeError, match="reference first"):
        StreamingSeqSLAM(SeqSLAMConfig(), frames)
