"""A number a user reads is right, or the run says why not (issue 36)."""

import warnings

import numpy as np
import pytest

from torchseq.ground_truth import GroundTruthError, load_ground_truth


def read_csv(tmp_path, text: str, n_reference=3, n_query=3, encoding="utf-8"):
    path = tmp_path / "gt.csv"
    path.write_bytes(text.encode(encoding))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gt = load_ground_truth(path, n_reference, n_query)
    return gt, [str(w.message) for w in caught]


def test_csv_with_a_byte_order_mark_reads_as_without(tmp_path):
    plain, _ = read_csv(tmp_path, "query,references\n0,0\n1,1 2\n2,2\n")
    bom, said = read_csv(tmp_path, "query,references\n0,0\n1,1 2\n2,2\n", encoding="utf-8-sig")
    assert (bom == plain).all() and plain[:, 1].tolist() == [False, True, True] and not said


@pytest.mark.parametrize("row", ["1,1,2", "1,1 2,7"])
def test_csv_row_with_extra_fields_is_refused_with_the_form_expected(tmp_path, row):
    with pytest.raises(GroundTruthError, match=r"gt.csv:3: 3 fields, expected 2 \(query, then "
                                               r"its references separated by spaces: '1,"):
        read_csv(tmp_path, f"query,references\n0,0\n{row}\n2,2\n")


def test_csv_header_with_extra_columns_is_refused(tmp_path):
    with pytest.raises(GroundTruthError, match="gt.csv:1: expected the header "
                                               "'query,references'.*'query,references,d'"):
        read_csv(tmp_path, "query,references,d\n0,0,1\n1,1,1\n2,2,1\n")


def test_nordland_headerless_one_based_table_is_read_and_said(tmp_path):
    # the layout of TimQuelch/seqslam's datasets/nordland_trimmed_resized/sample_ground_truth.csv
    gt, said = read_csv(tmp_path, "".join(f"{i},{i},15\n" for i in range(1, 6)), 5, 5)
    assert (gt == np.eye(5, dtype=bool)).all()
    assert said == [f"{tmp_path / 'gt.csv'}: read as headerless 1-based query,reference pairs "
                    f"(third column not used)"]
    gt, said = read_csv(tmp_path, "0,0\n1,1\n1,2\n2,2\n")  # 0-based, a query on two rows
    assert gt[:, 1].tolist() == [False, True, True] and "0-based" in said[0]


@pytest.mark.parametrize("text", ["0,0\n1,1\n", "2,2\n3,3\n4,4\n", "0,0\n1,1\n2,x\n",
                                  "0,0,1,2\n1,1,1,2\n2,2,1,2\n"])
def test_ambiguous_headerless_table_is_refused(tmp_path, text):
    with pytest.raises(GroundTruthError, match="gt.csv"):
        read_csv(tmp_path, text)
