"""The face's geometry: MediaPipe's landmark vocabulary, aumesh's template and face frame, alignment, measures."""
