//! Evaluation against ground truth: loop ground truth from poses or lists, precision-recall, plots.
