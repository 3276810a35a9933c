"""The numbers printed in the paper (Roman-Rivera et al. 2023), shown beside ours: measured on its
own recordings and hand-masked images, which are not public, so they are reference rows, never
recomputed."""

#: Table 3, on its own 200 hand-masked images: (row, mAP, mAP.50, mAP.75).
PAPER_TABLE3 = [("SphereDetection (ours), as reported by the paper", 0.512, 0.894, 0.529),
                ("CircleNet-HG, as reported by the paper", 0.491, 0.843, 0.512)]

#: Table 2 (metres): (scene, z threshold) -> (RMSE RANSAC, RMSE RANSAC centre with the z-filtered
#: points, RMSE barycentre with the z-filtered points).
PAPER_TABLE2 = {("E1", 3.0): (0.007343368, 0.007343368, 0.032156230),
                ("E1", 2.0): (0.007343368, 0.007343368, 0.020370757),
                ("E1", 1.5): (0.007343368, 0.007343368, 0.004612417),
                ("E2", 1.5): (0.366534813, 0.357131966, 0.041731429),
                ("E3", 1.5): (0.033177435, 0.033539393, 0.027763554)}

#: Its RANSAC iteration counts for Table 2: 1,000, and 10,000 for the cluttered scene E2.
PAPER_ITERATIONS = {"E2": 10_000}
PAPER_DEFAULT_ITERATIONS = 1000
