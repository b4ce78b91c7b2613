"""A small fake of Event-LAB's calling convention, written from its source (not imported).

From EventLAB-Team/Event-LAB: ``eventlab_run.py`` (the loop over ``timewindow_list``:
format_data, build_execute, run, parse_results, cleanup), ``baselines/get_baseline.py``
(baselines built with no arguments), ``baselines/EventBaselineLab.py`` (``EventBaseline``:
``K_list``, ``run_metrics`` turning a distance matrix into a similarity by ``max - array``
and scoring recall@K with VPR_Tutorial's ``recallAtK``) and ``datasets/dataloader.py``
(``get_dataset_info()`` keys). recall@K follows VPR_Tutorial's ``evaluation/metrics.py``:
queries without a true match are dropped, the K highest similarities of ``argsort`` count.
"""

import numpy as np


def recall_at_k(S, GT, K=1):
    """VPR_Tutorial's recallAtK (no GTsoft): (R, Q) similarity, (R, Q) 0/1 ground truth."""
    GT = GT.astype(bool)
    keep = GT.sum(0) > 0
    S, GT = S[:, keep], GT[:, keep]
    i = S.argsort(0)[-K:, :]
    j = np.tile(np.arange(i.shape[1]), [K, 1])
    return np.sum(GT[i, j].sum(0) > 0) / GT.shape[1]


class FakeEventBaseline:
    """Event-LAB's EventBaseline: the metric side every baseline inherits."""

    def __init__(self):
        self.K_list = [1, 5, 10, 15, 20, 25]
        self.scored = []   # (name, R@1, ...) per matrix, as run_metrics would tabulate
        self.saved = []

    def run_metrics(self, all_names, all_arrays, GThard, timestamp, run_name, ref_query,
                    matrix_type="distance", outdir=None, tolerance=0):
        assert tolerance == 0  # create_GTtol with 0 leaves the ground truth as it is
        rows = []
        for name, array in zip(all_names, all_arrays):
            assert array.shape == GThard.shape, (array.shape, GThard.shape)
            if matrix_type == "distance":
                array = array.max() - array
            recalls = [recall_at_k(array, GThard, k) for k in self.K_list]
            rows.append({"run_name": run_name, "ref_query": ref_query, "array_name": name,
                         "R@1": recalls[0], "R@5": recalls[1]})
        self.scored += rows
        return rows, {}

    def save_results(self, rows, pr_curves, run_name, ref_query):
        self.saved.append((run_name, ref_query, len(rows)))


class FakeSequence:
    """Event-LAB's EventDataset, as far as a baseline sees it."""

    def __init__(self, dataset, sequence, hdf5_path, timewindows):
        self.timewindow_list = list(timewindows)
        self._info = {"dataset_name": dataset, "sequence_name": sequence,
                      "hdf5_path": str(hdf5_path)}

    def get_dataset_info(self):
        return dict(self._info)


def eventlab_run(baseline, config, dataset_config, reference, query, gt_file):
    """The body of eventlab_run.main once the baseline is built."""
    for timewindow in reference.timewindow_list:
        baseline.format_data(config, dataset_config, reference, query, timewindow)
        baseline.build_execute(config, dataset_config, gt_file)
        baseline.run()
        baseline.parse_results(gt_file)
        baseline.cleanup()
