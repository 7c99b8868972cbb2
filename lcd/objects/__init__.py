"""Object detectors: COCO SSD-MobileNet-v2 (OpenCV DNN, the embedded default), ONNX Runtime models,
and the ground-truth oracle of synthetic scenes; plus the paper's object filter."""
